"""Garbage collection between ticks: no collection inside a tick, garbage still collected, collector restored."""

from __future__ import annotations

import gc
import weakref
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from openral_core import GarbageCollection, SensorReaderConfig
from openral_hal.testing import RecordingHAL
from openral_rskill.testing import ScriptedSkill
from openral_runner.gc_policy import BACKLOG_FACTOR, MIN_IDLE_S, BetweenTicksCollector
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import FakeClock, ScriptedReader
from openral_world_state import WorldStateAggregator

JOINTS = ["j0", "j1"]
CYCLES_PER_STEP = 3000  # several of Python's default 700-allocation thresholds per tick


class Node:
    """One half of a reference cycle: only the cyclic collector can free it."""

    def __init__(self) -> None:
        self.other: Node | None = None


class GarbageCycles:
    """Makes cyclic garbage during each step and watches what the collector does meanwhile."""

    def __init__(self) -> None:
        self.alive: weakref.WeakSet[Node] = weakref.WeakSet()
        self.in_step = False
        self.collections_in_step = 0
        self.collector_enabled_in_step: list[bool] = []
        self.frozen_in_step: list[int] = []

    def on_step(self, _index: int) -> None:
        self.in_step = True
        self.collector_enabled_in_step.append(gc.isenabled())
        self.frozen_in_step.append(gc.get_freeze_count())
        for _ in range(CYCLES_PER_STEP):
            a, b = Node(), Node()
            a.other, b.other = b, a
            self.alive.add(a)
        self.in_step = False

    def on_gc(self, phase: str, _info: dict[str, Any]) -> None:
        if phase == "start" and self.in_step:
            self.collections_in_step += 1


@pytest.fixture
def cycles() -> Iterator[GarbageCycles]:
    watcher = GarbageCycles()
    gc.callbacks.append(watcher.on_gc)
    was_enabled = gc.isenabled()
    gc.enable()
    yield watcher
    gc.callbacks.remove(watcher.on_gc)
    if not was_enabled:
        gc.disable()


def build(
    clock: FakeClock, watcher: GarbageCycles, policy: GarbageCollection, on_step: Callable[[int], None] | None = None
) -> HardwareRunner:
    skill = ScriptedSkill(JOINTS, on_step=on_step or watcher.on_step)
    skill.configure()
    skill.activate()
    reader = ScriptedReader("front", clock)
    runner = HardwareRunner(
        hal=RecordingHAL(JOINTS, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(
            joint_max_age_ms=100.0, sensors=[SensorReaderConfig(sensor_id="front")], clock=clock.now_ns
        ),
        sensor_readers=[reader],
        rate_hz=50.0,
        clock=clock,
        garbage_collection=policy,
    )
    runner.activate()
    return runner


def test_between_ticks_no_collection_lands_inside_a_step_and_garbage_is_still_freed(cycles: GarbageCycles) -> None:
    runner = build(FakeClock(), cycles, GarbageCollection.BETWEEN_TICKS)
    try:
        runner.run(20)
    finally:
        runner.deactivate()
    assert cycles.collections_in_step == 0
    assert not any(cycles.collector_enabled_in_step)
    assert min(cycles.frozen_in_step) > 0  # what was alive at the start is left out of every pass
    report = runner.metadata["gc"]
    assert sum(report["collections"]) >= 20  # each step's garbage crosses the threshold
    # 20 steps made 60,000 cycles; collected after each tick, at most the last step's can be left.
    assert len(cycles.alive) <= CYCLES_PER_STEP
    assert gc.isenabled()
    assert gc.get_freeze_count() == 0


def test_automatic_collection_does_land_inside_steps(cycles: GarbageCycles) -> None:
    runner = build(FakeClock(), cycles, GarbageCollection.AUTOMATIC)
    try:
        runner.run(5)
    finally:
        runner.deactivate()
    assert cycles.collections_in_step > 0  # what the default policy exists to prevent
    assert all(cycles.collector_enabled_in_step)
    assert "gc" not in runner.metadata


def test_the_collector_is_restored_when_the_run_is_interrupted(cycles: GarbageCycles) -> None:
    clock = FakeClock()

    def interrupt(index: int) -> None:
        cycles.on_step(index)
        if index == 3:
            raise KeyboardInterrupt  # not a skill fault: it ends the run

    runner = build(clock, cycles, GarbageCollection.BETWEEN_TICKS, on_step=interrupt)
    try:
        with pytest.raises(KeyboardInterrupt):
            runner.run(10)
    finally:
        runner.deactivate()
    assert gc.isenabled()
    assert gc.get_freeze_count() == 0


def test_collection_waits_for_idle_time_unless_the_backlog_grows() -> None:
    collector = BetweenTicksCollector()
    was_enabled = gc.isenabled()
    collector.start()
    try:
        threshold = gc.get_threshold()[0]
        keep = [[] for _ in range(threshold + 10)]  # tracked containers push the young count over the threshold
        assert collector.collect_if_due(idle_s=MIN_IDLE_S / 2) is None
        assert collector.collect_if_due(idle_s=MIN_IDLE_S * 2) == 0
        keep += [[] for _ in range(BACKLOG_FACTOR * threshold + 10)]
        assert collector.collect_if_due(idle_s=0.0) is not None  # a loop with no idle time still collects
        assert collector.collections[0] + collector.collections[1] + collector.collections[2] == 2
        del keep
    finally:
        collector.stop()
    assert gc.isenabled() == was_enabled
