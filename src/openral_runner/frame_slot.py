"""``LatestFrameSlot``: the latest-frame mailbox every capture backend shares.

A capture thread (or callback) ``publish``es frames; the tick thread peeks with
``read_latest`` without ever blocking on the device. Only a reference is swapped under the
lock, so pixels are never copied here. A capture failure is latched with ``fail`` and raised
on the next read, so a dead camera is reported, not silently served as a frozen frame.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from types import TracebackType
from typing import Self

import numpy as np
import structlog

from openral_core import FrameEncoding, ROSPerceptionStale, ROSRuntimeError, SensorFrame

_log = structlog.get_logger(__name__)

_FPS_SMOOTHING = 0.1
"""Weight of the newest inter-frame interval in the delivered-fps estimate."""


class LatestFrameSlot:
    """Holds one sensor's freshest frame and the reader's open/failed state.

    Args:
        sensor_id: The sensor, for error messages.
        default_max_age_ms: Age limit used when ``read_latest`` is given none.
        clock_ns: Clock the frames' ``stamp_ns`` use (``time.monotonic_ns``).
    """

    def __init__(
        self,
        sensor_id: str,
        *,
        default_max_age_ms: float,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if not default_max_age_ms > 0:
            raise ValueError(f"default_max_age_ms must be positive, got {default_max_age_ms}")
        self.sensor_id = sensor_id
        self.default_max_age_ms = default_max_age_ms
        self._clock_ns = clock_ns
        self._cond = threading.Condition(threading.Lock())
        self._frame: SensorFrame | None = None
        self._error: ROSRuntimeError | None = None
        self._open = False
        self._published = 0
        self._last_stamp_ns: int | None = None
        self._interval_ns: float | None = None

    # -- capture side --------------------------------------------------------------------

    def open(self) -> None:
        """Accept frames; forget any previous frame and error."""
        with self._cond:
            self._open = True
            self._frame = None
            self._error = None
            self._published = 0
            self._last_stamp_ns = None
            self._interval_ns = None

    def close(self) -> None:
        """Stop serving frames; readers get ``ROSRuntimeError`` until reopened."""
        with self._cond:
            self._open = False
            self._frame = None
            self._cond.notify_all()

    def publish(self, frame: SensorFrame) -> None:
        """Make ``frame`` the latest (called from the capture thread)."""
        with self._cond:
            if not self._open:
                return
            last = self._last_stamp_ns
            if last is not None and frame.stamp_ns > last:
                interval = frame.stamp_ns - last
                previous = self._interval_ns
                self._interval_ns = interval if previous is None else previous + _FPS_SMOOTHING * (interval - previous)
            self._last_stamp_ns = frame.stamp_ns
            self._frame = frame
            self._published += 1
            self._cond.notify_all()

    def fail(self, error: ROSRuntimeError) -> None:
        """Latch a capture failure; every read raises it until the slot is reopened."""
        with self._cond:
            if self._error is None:
                self._error = error
            self._cond.notify_all()

    # -- reading side --------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()``."""
        return self._open

    @property
    def frames_published(self) -> int:
        """Frames received since ``open()``."""
        return self._published

    @property
    def delivered_fps(self) -> float:
        """Smoothed rate of frames actually captured, from capture stamps (0 before two frames)."""
        interval = self._interval_ns
        return 1e9 / interval if interval else 0.0

    @property
    def error(self) -> ROSRuntimeError | None:
        """The latched capture failure, if any."""
        return self._error

    def peek(self) -> SensorFrame | None:
        """The latest frame regardless of age, or ``None`` (never raises)."""
        return self._frame

    def read_latest(self, max_age_ms: float | None = None) -> SensorFrame:
        """The latest frame if it is fresh enough.

        Raises:
            ROSRuntimeError: The reader is closed, or capture failed (latched error).
            ROSPerceptionStale: No frame yet, or the latest is older than the limit.
        """
        with self._cond:
            frame, error, is_open = self._frame, self._error, self._open
        if not is_open:
            raise ROSRuntimeError(f"sensor '{self.sensor_id}' is closed: call open() first")
        if error is not None:
            raise error
        limit = self.default_max_age_ms if max_age_ms is None else max_age_ms
        if frame is None:
            raise ROSPerceptionStale(self.sensor_id, age_ms=None, max_age_ms=limit)
        age_ms = (self._clock_ns() - frame.stamp_ns) / 1e6
        if age_ms > limit:
            raise ROSPerceptionStale(self.sensor_id, age_ms=age_ms, max_age_ms=limit)
        return frame

    def read_synced(self, deadline_ns: int, *, newer_than_ns: int = 0) -> SensorFrame:
        """A frame captured after ``newer_than_ns``, waiting at most until ``deadline_ns``.

        Raises:
            ROSRuntimeError: The reader is closed, or capture failed.
            ROSPerceptionStale: No such frame arrived by the deadline.
        """
        frame = self.wait_for_frame(newer_than_ns=newer_than_ns, deadline_ns=deadline_ns)
        if frame is not None:
            return frame
        with self._cond:
            latest, error, is_open = self._frame, self._error, self._open
        if not is_open:
            raise ROSRuntimeError(f"sensor '{self.sensor_id}' is closed: call open() first")
        if error is not None:
            raise error
        age_ms = None if latest is None else (self._clock_ns() - latest.stamp_ns) / 1e6
        raise ROSPerceptionStale(self.sensor_id, age_ms=age_ms, max_age_ms=self.default_max_age_ms)

    def wait_for_frame(self, *, newer_than_ns: int, deadline_ns: int) -> SensorFrame | None:
        """Block until a frame captured after ``newer_than_ns`` arrives, or until ``deadline_ns``.

        Returns:
            That frame, or ``None`` at the deadline (also when closed or failed meanwhile).
        """
        with self._cond:
            while True:
                frame = self._frame
                if frame is not None and frame.stamp_ns > newer_than_ns:
                    return frame
                if not self._open or self._error is not None:
                    return None
                remaining_s = (deadline_ns - self._clock_ns()) / 1e9
                if remaining_s <= 0:
                    return None
                self._cond.wait(remaining_s)


def frame_from_array(
    sensor_id: str,
    pixels: np.ndarray,
    *,
    stamp_ns: int,
    seq: int,
    encoding: FrameEncoding = FrameEncoding.BGR8,
    frame_id: str | None = None,
) -> SensorFrame:
    """Wrap an ``(H, W, C)`` or ``(H, W)`` capture array as a frame without copying it."""
    height, width = pixels.shape[:2]
    return SensorFrame(
        sensor_id=sensor_id,
        stamp_ns=stamp_ns,
        width=width,
        height=height,
        encoding=encoding,
        seq=seq,
        frame_id=frame_id,
        data=pixels,
    )


class SlotReader(ABC):
    """The reading half of the ``SensorReader`` contract for backends that publish into a slot.

    A backend sets ``sensor_id`` and ``_slot`` and implements ``open``/``close``; reading,
    the context manager and the delivered-rate figures come from here.
    """

    sensor_id: str
    _slot: LatestFrameSlot

    @abstractmethod
    def open(self) -> None:
        """Acquire the device and start publishing frames into the slot. Idempotent."""

    @abstractmethod
    def close(self) -> None:
        """Stop capture and release the device. Idempotent."""

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()``."""
        return self._slot.is_open

    @property
    def delivered_fps(self) -> float:
        """Rate of frames actually captured, from capture stamps (0 before two frames)."""
        return self._slot.delivered_fps

    @property
    def frames_published(self) -> int:
        """Frames captured since ``open()``."""
        return self._slot.frames_published

    def read_latest(self, max_age_ms: float | None = None) -> SensorFrame:
        """The most recent frame, without waiting for a new one.

        Raises:
            ROSRuntimeError: The reader is closed, or capture failed (latched).
            ROSPerceptionStale: No frame yet, or the latest is older than the limit.
        """
        return self._slot.read_latest(max_age_ms)

    def read_synced(self, deadline_ns: int, *, newer_than_ns: int = 0) -> SensorFrame:
        """A frame captured after ``newer_than_ns``, waiting at most until ``deadline_ns``.

        Raises:
            ROSRuntimeError: The reader is closed, or capture failed.
            ROSPerceptionStale: No such frame by the deadline.
        """
        return self._slot.read_synced(deadline_ns, newer_than_ns=newer_than_ns)

    def _stop_worker(self, stop: threading.Event, thread: threading.Thread | None, *, timeout_s: float) -> None:
        """Signal the capture worker, close the slot and join the worker for at most ``timeout_s``."""
        stop.set()
        self._slot.close()
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                _log.warning("capture thread did not stop in time", sensor=self.sensor_id, thread=thread.name)

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
