"""read_synced_set: a multi-camera set within a skew bound, or a clear reason why not."""

from __future__ import annotations

import pytest

from openral_core import FrameEncoding, ROSPerceptionStale, ROSSyncError, SensorFrame
from openral_runner.sensor_reader import SensorReader, read_synced_set


class Clock:
    def __init__(self) -> None:
        self.ns = 10_000_000_000

    def __call__(self) -> int:
        return self.ns


class PeriodicCamera:
    """A fake camera capturing every ``period_ns`` from ``offset_ns``, on a shared fake clock."""

    def __init__(
        self, sensor_id: str, clock: Clock, *, period_ns: int, offset_ns: int = 0, dead_after_ns: int | None = None
    ):
        self.sensor_id = sensor_id
        self.clock = clock
        self.period_ns = period_ns
        self.offset_ns = offset_ns
        self.dead_after_ns = dead_after_ns
        self.is_open = True

    def _latest_stamp(self, now: int) -> int:
        if self.dead_after_ns is not None:
            now = min(now, self.dead_after_ns)
        return (now - self.offset_ns) // self.period_ns * self.period_ns + self.offset_ns

    def _frame(self, stamp: int) -> SensorFrame:
        return SensorFrame(
            sensor_id=self.sensor_id, stamp_ns=stamp, width=1, height=1, encoding=FrameEncoding.MONO8, data=b"\0"
        )

    def open(self) -> None: ...

    def close(self) -> None: ...

    def read_latest(self, max_age_ms: float | None = None) -> SensorFrame:
        stamp = self._latest_stamp(self.clock.ns)
        age = (self.clock.ns - stamp) / 1e6
        if max_age_ms is not None and age > max_age_ms:
            raise ROSPerceptionStale(self.sensor_id, age_ms=age, max_age_ms=max_age_ms)
        return self._frame(stamp)

    def read_synced(self, deadline_ns: int, *, newer_than_ns: int = 0) -> SensorFrame:
        # Like a latest-frame slot: the newest frame already captured if it is new enough, else the next one.
        nxt = max(self._latest_stamp(newer_than_ns) + self.period_ns, self._latest_stamp(self.clock.ns))
        if (self.dead_after_ns is not None and nxt > self.dead_after_ns) or nxt > deadline_ns:
            self.clock.ns = max(self.clock.ns, deadline_ns)
            raise ROSPerceptionStale(self.sensor_id, age_ms=None, max_age_ms=None)
        self.clock.ns = max(self.clock.ns, nxt)
        return self._frame(nxt)


def test_fakes_satisfy_the_protocol() -> None:
    assert isinstance(PeriodicCamera("a", Clock(), period_ns=1), SensorReader)


def test_aligned_cameras_return_immediately() -> None:
    clock = Clock()
    cams = [PeriodicCamera(n, clock, period_ns=33_000_000) for n in ("left", "right")]
    start = clock.ns
    frames = read_synced_set(cams, max_skew_ms=5, deadline_ns=clock.ns + 50_000_000, clock_ns=clock)
    assert frames["left"].stamp_ns == frames["right"].stamp_ns
    assert clock.ns == start  # nothing waited


@pytest.mark.parametrize("offset_ms", [3, 6, 27, 30])
def test_set_lies_within_the_skew_bound(offset_ms: int) -> None:
    clock = Clock()
    clock.ns += 1_000_000  # a moment after a "left" capture, before "right" catches up
    left = PeriodicCamera("left", clock, period_ns=33_000_000)
    right = PeriodicCamera("right", clock, period_ns=33_000_000, offset_ns=offset_ms * 1_000_000)
    wrist = PeriodicCamera("wrist", clock, period_ns=20_000_000, offset_ns=7_000_000)
    frames = read_synced_set([left, right, wrist], max_skew_ms=8, deadline_ns=clock.ns + 500_000_000, clock_ns=clock)
    stamps = [f.stamp_ns for f in frames.values()]
    assert max(stamps) - min(stamps) <= 8_000_000


def test_dead_camera_gives_a_sync_error_naming_it() -> None:
    clock = Clock()
    left = PeriodicCamera("left", clock, period_ns=10_000_000)
    frozen = PeriodicCamera("frozen", clock, period_ns=10_000_000, dead_after_ns=clock.ns - 40_000_000)
    with pytest.raises(ROSSyncError) as info:
        read_synced_set([left, frozen], max_skew_ms=5, deadline_ns=clock.ns + 30_000_000, clock_ns=clock)
    assert info.value.lagging == ("frozen",)
    assert info.value.skew_ms >= 40
    assert "frozen" in str(info.value)


def test_stale_camera_is_reported_before_syncing() -> None:
    clock = Clock()
    left = PeriodicCamera("left", clock, period_ns=10_000_000)
    frozen = PeriodicCamera("frozen", clock, period_ns=10_000_000, dead_after_ns=clock.ns - 400_000_000)
    with pytest.raises(ROSPerceptionStale):
        read_synced_set(
            [left, frozen], max_skew_ms=5, deadline_ns=clock.ns + 30_000_000, max_age_ms=100, clock_ns=clock
        )


def test_cameras_that_never_align_within_the_skew_fail_by_the_deadline() -> None:
    # Same 33 ms period, 16 ms apart: stamps always differ by 16 or 17 ms.
    clock = Clock()
    left = PeriodicCamera("left", clock, period_ns=33_000_000)
    right = PeriodicCamera("right", clock, period_ns=33_000_000, offset_ns=16_000_000)
    deadline = clock.ns + 200_000_000
    with pytest.raises(ROSSyncError):
        read_synced_set([left, right], max_skew_ms=8, deadline_ns=deadline, clock_ns=clock)
    assert clock.ns >= deadline  # it kept trying until the deadline, then said why
