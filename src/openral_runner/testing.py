"""Fakes for runner tests: a clock that never sleeps and a reader that serves scripted frames."""

from __future__ import annotations

from collections.abc import Callable

from openral_core import FrameEncoding, ROSPerceptionStale, ROSRuntimeError, SensorFrame


class FakeClock:
    """A manual clock: ``sleep_until`` jumps time forward instead of waiting.

    Components under test call ``advance`` to simulate work taking time. ``sleeps`` records
    every ``sleep_until`` target so tests can check the schedule.
    """

    def __init__(self, start_s: float = 100.0) -> None:
        self.t = start_s
        self.sleeps: list[float] = []

    def now(self) -> float:
        """Current fake time in seconds."""
        return self.t

    def now_ns(self) -> int:
        """Current fake time in nanoseconds (the stamp clock)."""
        return round(self.t * 1e9)

    def sleep_until(self, deadline_s: float) -> None:
        """Jump to ``deadline_s`` if it is in the future."""
        self.sleeps.append(deadline_s)
        self.t = max(self.t, deadline_s)

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` of fake time pass."""
        self.t += seconds


class ScriptedReader:
    """A ``SensorReader`` whose frames are made on demand, stamped on a fake clock.

    Args:
        sensor_id: Reader id.
        clock: Stamps frames with ``clock.now_ns()`` minus ``age_ms``.
        width / height: Frame size (BGR8 pixels, zero-filled bytes).
        age_ms: Age of each served frame; set it high to make the reader stale.
        max_age_ms: Default staleness limit.
        fail_open: Raised by ``open()`` when set.
        frame_period_ns: Capture period used by ``read_synced``.
    """

    def __init__(
        self,
        sensor_id: str,
        clock: FakeClock,
        *,
        width: int = 4,
        height: int = 3,
        age_ms: float = 1.0,
        max_age_ms: float = 100.0,
        fail_open: Exception | None = None,
        frame_period_ns: int = 33_333_333,
    ) -> None:
        self.sensor_id = sensor_id
        self.clock = clock
        self.width = width
        self.height = height
        self.age_ms = age_ms
        self.max_age_ms = max_age_ms
        self.fail_open = fail_open
        self.frame_period_ns = frame_period_ns
        self.open_calls = 0
        self.close_calls = 0
        self.on_read: Callable[[], None] | None = None
        self._open = False
        self._seq = 0
        self._pixels = bytes(width * height * 3)

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()``."""
        return self._open

    def open(self) -> None:
        """Open, or raise ``fail_open``."""
        self.open_calls += 1
        if self.fail_open is not None:
            raise self.fail_open
        self._open = True

    def close(self) -> None:
        """Close. Idempotent."""
        if self._open:
            self.close_calls += 1
        self._open = False

    def read_synced(self, deadline_ns: int, *, newer_than_ns: int = 0) -> SensorFrame:
        """Jump the fake clock to the next frame if it is due before ``deadline_ns``.

        Frames are captured every ``frame_period_ns`` from time 0 on the fake clock.
        """
        period = self.frame_period_ns
        next_stamp = (max(newer_than_ns, self.clock.now_ns() - round(self.age_ms * 1e6)) // period + 1) * period
        if next_stamp > deadline_ns:
            self.clock.sleep_until(deadline_ns / 1e9)
            raise ROSPerceptionStale(self.sensor_id, age_ms=None, max_age_ms=self.max_age_ms)
        self.clock.sleep_until(next_stamp / 1e9 + self.age_ms / 1e3)
        return self.read_latest()

    def read_latest(self, max_age_ms: float | None = None) -> SensorFrame:
        """A frame ``age_ms`` old, or ``ROSPerceptionStale`` if that exceeds the limit."""
        if not self._open:
            raise ROSRuntimeError(f"reader '{self.sensor_id}' is closed")
        if self.on_read is not None:
            self.on_read()
        limit = self.max_age_ms if max_age_ms is None else max_age_ms
        if self.age_ms > limit:
            raise ROSPerceptionStale(self.sensor_id, age_ms=self.age_ms, max_age_ms=limit)
        self._seq += 1
        return SensorFrame(
            sensor_id=self.sensor_id,
            stamp_ns=self.clock.now_ns() - round(self.age_ms * 1e6),
            width=self.width,
            height=self.height,
            encoding=FrameEncoding.BGR8,
            seq=self._seq,
            data=self._pixels,
        )
