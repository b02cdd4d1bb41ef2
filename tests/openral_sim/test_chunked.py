"""A chunking skill in simulation: the executor between it and the env, with reproducible virtual latency."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from openral_core import (
    Action,
    ExecutorConfig,
    RobotManifest,
    RSkillInfo,
    SimEnvironment,
    TickResult,
    VirtualLatency,
    WithheldReason,
    WorldState,
)
from openral_observability.observer import TickObserver
from openral_rskill.base import ChunkingSkillBase, RSkillBase
from openral_rskill.chunks import ChunkRequest
from openral_sim.envs.mock import MockParams, MockReachEnv
from openral_sim.runner import SimRunner


class ChunkOfSteps(RSkillBase):
    """Row j of a chunk observed at step k is [k, j]: what was executed when is readable from the action."""

    def __init__(self, robot: RobotManifest, rows: int) -> None:
        super().__init__()
        self.names = robot.joint_names
        self._info = RSkillInfo(skill_id="chunk_of_steps", chunk_size=rows)
        self.rows = rows
        self.resets: list[int | None] = []

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> ChunkOfSteps:
        return cls(robot, 5)

    @property
    def info(self) -> RSkillInfo:
        return self._info

    def _on_reset(self) -> None:
        self.resets.append(self.episode_seed)

    def _step_impl(self, world_state: WorldState) -> Action:
        step = float(world_state.stamp_ns)
        return Action(joint_names=self.names, targets=[[step * 0 + 0.01 * j, 0.0] for j in range(self.rows)])


class Steps(TickObserver):
    def __init__(self) -> None:
        self.ticks: list[TickResult] = []

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        if tick.step_idx is not None:
            self.ticks.append(tick)

    def close(self) -> None:
        return


def _run(latency: VirtualLatency, config: ExecutorConfig | None = None) -> tuple[SimRunner, Steps, ChunkOfSteps]:
    env = MockReachEnv(MockParams())
    scene = SimEnvironment(
        name="reach",
        env="mock",
        task="reach",
        success_key="is_success",
        max_steps=12,
        n_episodes=2,
        seed=4,
        virtual_latency=latency,
        executor=config or ExecutorConfig(),
    )
    skill = ChunkOfSteps(env.spec.action_manifest("mock"), 5)
    runner, steps = _run_skill(env, scene, skill)
    return runner, steps, skill


def _run_skill(env: MockReachEnv, scene: SimEnvironment, skill: RSkillBase) -> tuple[SimRunner, Steps]:
    """Run ``skill`` on the scene's episodes, every tick's result kept."""
    runner = SimRunner(env=env, scene=scene, skill=skill)
    steps = Steps()
    runner.observers.append(steps)
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        runner.run(max_ticks=100)
    finally:
        runner.deactivate()
    return runner, steps


def test_rows_arrive_after_the_virtual_delay_and_the_robot_holds_until_then() -> None:
    runner, steps, skill = _run(VirtualLatency(ticks=2))
    first = [t for t in steps.ticks if t.episode_idx == 0]
    assert [t.withheld_reason for t in first[:2]] == [WithheldReason.AWAITING_CHUNK] * 2
    assert not first[0].action_applied
    # At step 2 the chunk observed at step 0 is used from its row 2: two rows skipped for two ticks.
    assert first[2].sent_action == [0.02, 0.0]
    assert runner.executor is not None
    assert runner.executor.stats.delays_ticks[0] == 2
    assert runner.executor.stats.rows_skipped == sum(runner.executor.stats.delays_ticks)
    # The skill was reset with each episode's seed, on the executor, once per episode.
    assert skill.resets == [4, 5]


def test_the_same_seeds_give_the_same_ticks_with_jittered_latency() -> None:
    latency = VirtualLatency(ticks=1, jitter_ticks=2)
    _, first, _ = _run(latency)
    _, second, _ = _run(latency)
    assert [t.sent_action for t in first.ticks] == [t.sent_action for t in second.ticks]
    assert [t.withheld_reason for t in first.ticks] == [t.withheld_reason for t in second.ticks]


def test_stale_start_runs_each_chunk_from_its_first_row() -> None:
    runner, steps, _ = _run(VirtualLatency(ticks=2), ExecutorConfig(indexing="stale_start"))
    first = [t for t in steps.ticks if t.episode_idx == 0]
    assert first[2].sent_action == [0.0, 0.0]  # row 0, two ticks late
    assert runner.executor is not None
    assert runner.executor.stats.rows_skipped == 0
    assert np.isfinite(runner.episode_results[0].sum_reward)


class OvershootingChunks(ChunkingSkillBase):
    """Rows past the action box (the safety check clamps them); it reads the last 3 commands sent."""

    def __init__(self, robot: RobotManifest) -> None:
        super().__init__()
        self.names = robot.joint_names
        self._info = RSkillInfo(skill_id="overshooting_chunks", chunk_size=4, past_actions=3)
        self.asked: list[ChunkRequest] = []

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> OvershootingChunks:
        return cls(robot)

    @property
    def info(self) -> RSkillInfo:
        return self._info

    @property
    def action_names(self) -> list[str]:
        return list(self.names)

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        self.asked.append(request)
        k = request.obs_tick
        return np.array([[0.5 + 0.1 * (k + j), -0.01 * (k + j)] for j in range(4)])


def test_a_request_reads_the_commands_sent_after_the_safety_clamp_by_tick() -> None:
    env = MockReachEnv(MockParams())
    scene = SimEnvironment(
        name="reach", env="mock", task="reach", success_key="is_success", max_steps=12, n_episodes=2, seed=4,
        virtual_latency=VirtualLatency(ticks=1), executor=ExecutorConfig(margin_ticks=0),
    )  # fmt: skip
    skill = OvershootingChunks(env.spec.action_manifest("mock"))
    _, steps = _run_skill(env, scene, skill)
    sent = {t.tick_idx: t.sent_action for t in steps.ticks if t.sent_action is not None}
    assert any(t.requested_action != t.sent_action for t in steps.ticks if t.sent_action is not None)  # clamped
    episode_of = {t.tick_idx: t.episode_idx for t in steps.ticks}
    assert len(skill.asked) >= 6
    firsts = 0
    for request in skill.asked:
        episode = episode_of[request.obs_tick]
        before = [t for t in sorted(sent) if t < request.obs_tick and episode_of[t] == episode][-3:]
        assert request.past_ticks == tuple(before)  # this episode's, oldest first
        assert request.past.tolist() == [sent[t] for t in before]  # as sent: clamped into the box
        firsts += not before
    assert firsts == 2  # each episode's first request reads no command
