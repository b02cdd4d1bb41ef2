"""Cadence helpers: precise sleeping and the clock seam the runner schedules against."""

from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

_BUSY_LOOP_THRESHOLD_S = 1e-3
"""The final stretch of a sleep is busy-waited: ``time.sleep`` can overshoot by tens of µs to ms."""


def precise_sleep(duration_s: float) -> None:
    """Sleep ``duration_s`` seconds: ``time.sleep`` for the bulk, busy-wait for the last ~1 ms.

    A non-positive duration returns at once.
    """
    if duration_s <= 0:
        return
    sleep_until(time.perf_counter() + duration_s)


def sleep_until(deadline_perf_counter_s: float) -> None:
    """Return at the absolute ``time.perf_counter()`` instant given (at once if it has passed)."""
    remaining = deadline_perf_counter_s - time.perf_counter()
    if remaining <= 0:
        return
    if remaining > _BUSY_LOOP_THRESHOLD_S:
        time.sleep(remaining - _BUSY_LOOP_THRESHOLD_S)
    while time.perf_counter() < deadline_perf_counter_s:
        pass


@runtime_checkable
class Clock(Protocol):
    """Where a runner reads time and waits. Swapped for a fake clock in tests (no real sleeping).

    ``now`` is in seconds on the scheduling clock; ``now_ns`` is in nanoseconds on the clock
    sensor and joint-state stamps use (``time.monotonic_ns`` in production).
    """

    def now(self) -> float: ...

    def now_ns(self) -> int: ...

    def sleep_until(self, deadline_s: float) -> None: ...


class SystemClock:
    """The real clock: ``time.perf_counter`` for scheduling, ``time.monotonic_ns`` for stamps."""

    now = staticmethod(time.perf_counter)
    now_ns = staticmethod(time.monotonic_ns)
    sleep_until = staticmethod(sleep_until)
