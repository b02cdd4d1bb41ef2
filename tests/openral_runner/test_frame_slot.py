"""LatestFrameSlot: non-blocking latest frame, staleness from capture stamps, latched failures."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from openral_core import ROSPerceptionStale, ROSRuntimeError
from openral_runner.frame_slot import LatestFrameSlot, frame_from_array


class Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def frame(stamp_ns: int, seq: int = 0):
    return frame_from_array("cam", np.zeros((2, 3, 3), np.uint8), stamp_ns=stamp_ns, seq=seq)


def test_read_contract_closed_empty_fresh_stale() -> None:
    clock = Clock()
    slot = LatestFrameSlot("cam", default_max_age_ms=50, clock_ns=clock)
    with pytest.raises(ROSRuntimeError, match="closed"):
        slot.read_latest()
    slot.open()
    with pytest.raises(ROSPerceptionStale, match="not delivered"):
        slot.read_latest()
    f = frame(clock.ns - 10_000_000)
    slot.publish(f)
    assert slot.read_latest() is f
    clock.ns += 45_000_000  # now 55 ms old
    with pytest.raises(ROSPerceptionStale) as info:
        slot.read_latest()
    assert info.value.age_ms == pytest.approx(55.0)
    assert slot.read_latest(max_age_ms=60) is f
    slot.close()
    with pytest.raises(ROSRuntimeError):
        slot.read_latest()


def test_staleness_is_measured_from_capture_not_arrival() -> None:
    clock = Clock()
    slot = LatestFrameSlot("cam", default_max_age_ms=50, clock_ns=clock)
    slot.open()
    slot.publish(frame(clock.ns - 80_000_000))  # arrives now, captured 80 ms ago
    with pytest.raises(ROSPerceptionStale):
        slot.read_latest()


def test_failure_is_latched_until_reopen() -> None:
    clock = Clock()
    slot = LatestFrameSlot("cam", default_max_age_ms=50, clock_ns=clock)
    slot.open()
    slot.publish(frame(clock.ns))
    slot.fail(ROSRuntimeError("device unplugged"))
    slot.publish(frame(clock.ns, seq=1))
    with pytest.raises(ROSRuntimeError, match="unplugged"):
        slot.read_latest()
    slot.open()
    with pytest.raises(ROSPerceptionStale):
        slot.read_latest()


def test_delivered_fps_from_capture_stamps() -> None:
    clock = Clock()
    slot = LatestFrameSlot("cam", default_max_age_ms=50, clock_ns=clock)
    slot.open()
    for i in range(50):
        slot.publish(frame(i * 40_000_000, seq=i))  # 25 fps
    assert slot.delivered_fps == pytest.approx(25.0)
    assert slot.frames_published == 50


def test_read_synced_waits_for_a_newer_frame_and_times_out() -> None:
    slot = LatestFrameSlot("cam", default_max_age_ms=500)
    slot.open()
    first = frame(time.monotonic_ns())
    slot.publish(first)
    later = frame(first.stamp_ns + 1, seq=1)
    timer = threading.Timer(0.05, slot.publish, args=(later,))
    timer.start()
    got = slot.read_synced(time.monotonic_ns() + 2_000_000_000, newer_than_ns=first.stamp_ns)
    assert got is later
    with pytest.raises(ROSPerceptionStale):
        slot.read_synced(time.monotonic_ns() + 20_000_000, newer_than_ns=later.stamp_ns)
    timer.join()


def test_frame_from_array_is_zero_copy() -> None:
    pixels = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    f = frame_from_array("cam", pixels, stamp_ns=1, seq=0)
    assert (f.width, f.height) == (5, 4)
    assert f.as_array() is pixels
