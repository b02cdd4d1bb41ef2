"""A chunking skill on the hardware runner: the tick never waits, starvation stops safely, resets go to the worker."""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

from openral_core import Action, ExecutorConfig, RobotManifest, RSkillInfo, StopReason, WithheldReason, WorldState
from openral_hal.testing import RecordingHAL
from openral_rskill.base import RSkillBase
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import FakeClock
from openral_world_state import WorldStateAggregator

JOINTS = ["a", "b"]


class GatedChunks(RSkillBase):
    """Returns a 4-row chunk [[i, 0]] once the test lets each inference through."""

    def __init__(self) -> None:
        super().__init__()
        self._info = RSkillInfo(skill_id="gated", chunk_size=4)
        self.gate = threading.Semaphore(0)
        self.calls: list[str] = []

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> GatedChunks:
        return cls()

    @property
    def info(self) -> RSkillInfo:
        return self._info

    def _on_reset(self) -> None:
        self.calls.append("reset")

    def _step_impl(self, world_state: WorldState) -> Action:
        self.calls.append("infer")
        self.gate.acquire()
        return Action(joint_names=JOINTS, targets=[[0.1 * i, 0.0] for i in range(4)])


def _runner(skill: GatedChunks, config: ExecutorConfig) -> tuple[HardwareRunner, RecordingHAL]:
    clock = FakeClock()
    hal = RecordingHAL(JOINTS, clock_ns=clock.now_ns)
    runner = HardwareRunner(
        hal=hal,
        skill=skill,
        aggregator=WorldStateAggregator(clock=clock.now_ns),
        rate_hz=30,
        clock=clock,
        thumbnail_hz=0.0,
        executor=config,
        action_names=JOINTS,
    )
    skill.configure()
    skill.activate()
    return runner, hal


def test_the_tick_runs_on_while_the_policy_infers_and_starvation_stops_safely() -> None:
    skill = GatedChunks()
    runner, hal = _runner(skill, ExecutorConfig(max_starved_ticks=2, fallback="stop", margin_ticks=0))
    runner.activate()
    try:
        first = runner.run(3)  # the first inference is stuck: three ticks, nothing to send or hold
        assert [t.withheld_reason for t in runner.recent_ticks] == [WithheldReason.AWAITING_CHUNK] * 3
        assert first.stop_reason == StopReason.MAX_TICKS
        skill.gate.release()
        deadline = time.monotonic() + 5
        while runner.executor is not None and runner.executor.results_waiting == 0:
            assert time.monotonic() < deadline
            time.sleep(0.001)
        result = runner.run(20)  # rows, then the next inference is stuck: hold twice, then stop
    finally:
        runner.deactivate()
    reasons = [t.withheld_reason for t in runner.recent_ticks]
    assert result.stop_reason == StopReason.FAULTS
    assert reasons[-1] == WithheldReason.STARVED
    assert reasons.count(None) >= 1  # the chunk's rows and the held target were sent
    sent = [t.sent_action for t in runner.recent_ticks if t.action_applied]
    assert sent[-1] == sent[-2]  # the last target held while starved
    assert hal.sent  # the robot was commanded only with rows of an arrived chunk
    assert result.metadata["executor"]["starved_ticks"] >= 2


def test_an_episode_reset_runs_on_the_worker_after_the_inference_under_way() -> None:
    skill = GatedChunks()
    runner, _hal = _runner(skill, ExecutorConfig())
    runner.activate()
    try:
        runner.run(1)
        runner.episode_start("next")
        skill.gate.release(3)
        deadline = time.monotonic() + 5
        while "reset" not in skill.calls:
            assert time.monotonic() < deadline
            time.sleep(0.001)
    finally:
        runner.deactivate()
    assert skill.calls[:2] == ["infer", "reset"]
