"""QueuedObserver: the tick thread only appends; the worker sees ticks and episodes in order and drains on close."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from openral_core import ROSConfigError, TickResult, WorldState
from openral_observability.queued_observer import QueuedObserver


def _tick(idx: int) -> TickResult:
    return TickResult(tick_idx=idx, start_ns=idx, tick_ms=1.0)


class Log(QueuedObserver):
    def __init__(self, **kwargs: Any) -> None:
        self.seen: list[Any] = []
        self.gate = threading.Event()
        self.gate.set()
        self.closed_after: list[Any] | None = None
        self.dropped: list[int] = []
        super().__init__(name="test-log", **kwargs)

    def handle_tick(self, tick: TickResult, world: WorldState | None) -> None:
        self.gate.wait(10)
        if tick.tick_idx == 13:
            raise ValueError("a bad tick")
        self.seen.append(("tick", tick.tick_idx))

    def handle_episode_start(self, episode_idx: int, task: str) -> None:
        self.seen.append(("start", episode_idx, task))

    def handle_episode_end(self, episode_idx: int, *, success: bool, keep: bool) -> None:
        self.seen.append(("end", episode_idx, success, keep))

    def handle_close(self) -> None:
        self.closed_after = list(self.seen)

    def on_overflow(self, tick: TickResult) -> None:
        self.dropped.append(tick.tick_idx)


def test_ticks_and_episode_boundaries_reach_the_worker_in_order_and_close_drains() -> None:
    log = Log()
    log.on_tick(_tick(0), None)
    log.on_episode_start(0, "pick")
    log.on_tick(_tick(1), None)
    log.on_tick(_tick(2), None)
    log.on_episode_end(0, success=True)
    log.on_tick(_tick(3), None)
    log.on_episode_end(1, success=False, keep=False)
    log.close()
    expected = [
        ("tick", 0),
        ("start", 0, "pick"),
        ("tick", 1),
        ("tick", 2),
        ("end", 0, True, True),
        ("tick", 3),
        ("end", 1, False, False),
    ]
    assert log.seen == expected
    assert log.closed_after == expected  # handle_close ran after everything queued
    assert log.handled == 4
    log.close()  # idempotent
    log.on_tick(_tick(4), None)  # after close: ignored, not an error
    assert log.handled == 4


def test_a_full_queue_drops_the_oldest_tick_counts_it_and_keeps_episode_boundaries() -> None:
    log = Log(max_queue=4, flush_interval_s=10.0)
    log.gate.clear()  # the worker is stuck on the first tick it takes
    log.on_tick(_tick(0), None)
    log.on_episode_start(0, "pick")
    for idx in range(1, 9):
        log.on_tick(_tick(idx), None)
    assert log.queued <= 4
    assert log.overflowed == len(log.dropped) > 0
    log.gate.set()
    log.close()
    ticks = [item[1] for item in log.seen if item[0] == "tick"]
    assert ("start", 0, "pick") in log.seen
    assert sorted(ticks + log.dropped) == list(range(9))
    assert ticks == sorted(ticks)
    assert ticks[-4:] == [5, 6, 7, 8]  # the newest ticks survive


def test_a_failing_handler_is_counted_and_the_worker_goes_on() -> None:
    log = Log()
    for idx in (12, 13, 14):
        log.on_tick(_tick(idx), None)
    log.close()
    assert log.errors == 1
    assert log.seen == [("tick", 12), ("tick", 14)]


@pytest.mark.parametrize(("kwargs", "field"), [({"max_queue": 1}, "max_queue"), ({"flush_interval_s": 0}, "flush")])
def test_bad_settings_name_the_field(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(ROSConfigError, match=field):
        Log(**kwargs)
