"""Real time (``virtual_latency: measured``): the wall clock paces the world; a slow policy loses what a robot would.

The proof runs on a task where delay visibly matters: a target drifts away at a seeded speed and
the arm (an absolute position) must stay within a tolerance of it. A chunking tracker commands
the target it observed, so every tick of lag costs distance: the executor's steady lag is at
most 3 ticks for delays of 0 to 2 ticks (every seed succeeds), 5 for 3 ticks (about half do).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from statistics import median
from typing import Any

import numpy as np
import pytest

from openral_core import (
    Action,
    EpisodeResult,
    ExecutorConfig,
    RealTimeStats,
    RobotManifest,
    ROSConfigError,
    RSkillInfo,
    SimEnvironment,
    VirtualLatency,
    WorldState,
)
from openral_rskill.base import RSkillBase
from openral_sim.env import EnvSpec, SimObservation, SimStep
from openral_sim.evaluation import summarize, wilson_interval
from openral_sim.runner import SimRunner

CONTROL_HZ = 50.0
PERIOD_S = 1.0 / CONTROL_HZ
HOLD_STEPS = 20
"""Steps the arm must stay within the tolerance to succeed."""


class DriftEnv:
    """A target drifting at a seeded speed from 0; the arm is where it was last commanded.

    Success once the arm has stayed within ``tolerance`` for ``HOLD_STEPS`` steps; falling behind
    further ends the episode (terminated, a failure).
    """

    def __init__(self, speeds: tuple[float, float] = (0.1, 0.24), tolerance: float = 1.0) -> None:
        self.spec = EnvSpec(
            state_names=("x", "target"),
            action_names=("x",),
            action_low=(-100.0,),
            action_high=(100.0,),
            action_kind="absolute",
            control_hz=CONTROL_HZ,
        )
        self.speeds = speeds
        self.tolerance = tolerance
        self._speed = 0.0
        self._steps = 0
        self._x = 0.0

    def reset(self, seed: int) -> SimObservation:
        self._speed = float(np.random.default_rng(seed).uniform(*self.speeds))
        self._steps = 0
        self._x = 0.0
        return self._observe(success=False)

    def step(self, action: np.ndarray) -> SimStep:
        self._steps += 1
        self._x = float(action[0])
        behind = abs(self._speed * self._steps - self._x) > self.tolerance
        success = not behind and self._steps >= HOLD_STEPS
        return SimStep(self._observe(success=success), reward=0.0, terminated=behind, truncated=False)

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        return np.zeros((height, width, 3), np.uint8)

    def close(self) -> None:
        pass

    def _observe(self, *, success: bool) -> SimObservation:
        state = np.array([self._x, self._speed * self._steps])
        return SimObservation(state=state, privileged={}, info={"is_success": success})


class Tracker(RSkillBase):
    """Commands the target it observes, for ``rows`` ticks; each inference takes ``infer_s`` of wall time."""

    def __init__(self, robot: RobotManifest, *, rows: int, infer_s: float) -> None:
        super().__init__()
        self.names = robot.joint_names
        self.rows = rows
        self.infer_s = infer_s
        self._info = RSkillInfo(skill_id="tracker", chunk_size=rows)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Tracker:
        return cls(robot, rows=int(params["rows"]), infer_s=float(params["infer_s"]))

    @property
    def info(self) -> RSkillInfo:
        return self._info

    def _step_impl(self, world_state: WorldState) -> Action:
        if self.infer_s:
            time.sleep(self.infer_s)  # the policy's compute time, not a wait for anything
        assert world_state.joint_state is not None
        target = world_state.joint_state.positions[1]
        return Action(joint_names=self.names, targets=[[target]] * self.rows)


def _evaluate(
    latency: VirtualLatency | str,
    *,
    rows: int,
    infer_s: float,
    n_episodes: int,
    speeds: tuple[float, float] = (0.1, 0.24),
) -> SimRunner:
    env = DriftEnv(speeds)
    scene = SimEnvironment.model_validate(
        {
            "name": "drift",
            "env": "drift",
            "task": "keep up",
            "max_steps": HOLD_STEPS,
            "n_episodes": n_episodes,
            "seed": 0,
            "virtual_latency": latency,
            "executor": ExecutorConfig(),
        }
    )
    skill = Tracker(env.spec.action_manifest("drift"), rows=rows, infer_s=infer_s)
    runner = SimRunner(env=env, scene=scene, skill=skill)
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        runner.run(max_ticks=n_episodes * (HOLD_STEPS + 1) + 1)
    finally:
        runner.deactivate()
        skill.shutdown()
    return runner


def _rate(runner: SimRunner) -> tuple[int, int]:
    return sum(e.success for e in runner.episode_results), len(runner.episode_results)


def test_a_late_tick_steps_the_world_through_its_skipped_slots_so_sim_time_keeps_wall_time() -> None:
    # A non-chunking skill infers on the tick for 2.5 slots: each tick skips two slots, held.
    runner = _evaluate("measured", rows=1, infer_s=2.5 * PERIOD_S, n_episodes=2, speeds=(0.0, 0.0))
    assert [e.ended_by for e in runner.episode_results] == ["success", "success"]
    for episode in runner.episode_results:
        live = episode.real_time
        assert live is not None
        assert live.policy_ticks + live.held_slots == episode.steps == HOLD_STEPS
        assert live.held_slots >= 2 * (live.policy_ticks - 1)
        assert live.fresh_ticks == live.policy_ticks
        assert live.stale_ticks == 0
        assert live.stale_or_held_ratio == pytest.approx(live.held_slots / episode.steps)
        # Simulated time (steps at the control rate) kept up with the wall clock, within a slot or so.
        assert abs(episode.steps * PERIOD_S - live.wall_s) <= 2 * PERIOD_S
        assert live.steps_per_s == pytest.approx(episode.steps / live.wall_s)
        assert live.commands_per_s < CONTROL_HZ / 2.5


def test_under_virtual_latency_the_same_slow_skill_loses_no_steps_and_reports_no_wall_clock_figures() -> None:
    runner = _evaluate(VirtualLatency(), rows=1, infer_s=2.5 * PERIOD_S, n_episodes=1, speeds=(0.0, 0.0))
    (episode,) = runner.episode_results
    assert episode.real_time is None
    assert episode.ended_by == "success"
    assert episode.steps == HOLD_STEPS


def test_the_default_virtual_latency_stays_deterministic() -> None:
    first = _evaluate(VirtualLatency(ticks=3), rows=5, infer_s=0.0, n_episodes=12)
    second = _evaluate(VirtualLatency(ticks=3), rows=5, infer_s=0.0, n_episodes=12)
    assert [e.outcome() for e in first.episode_results] == [e.outcome() for e in second.episode_results]
    assert all(e.real_time is None for e in first.episode_results)
    assert 0 < _rate(first)[0] < 12  # the task separates delays: some seeds fail at 3 ticks


def test_virtual_delays_order_the_task_as_the_proof_needs() -> None:
    """Delays 0 to 2 lose nothing here, 3 loses about half the seeds, 4 more: what the slow proof relies on."""
    rates = [_rate(_evaluate(VirtualLatency(ticks=d), rows=5, infer_s=0.0, n_episodes=30))[0] for d in range(5)]
    assert rates[0] == rates[1] == rates[2] == 30
    assert 5 <= rates[3] <= 25
    assert rates[4] < rates[3]


def test_stale_start_rows_are_counted_stale_and_tick_indexed_rows_never() -> None:
    env = DriftEnv((0.0, 0.0))
    scene = SimEnvironment(
        name="drift",
        env="drift",
        task="keep up",
        max_steps=HOLD_STEPS,
        n_episodes=1,
        virtual_latency=VirtualLatency(ticks=2),
        executor=ExecutorConfig(indexing="stale_start"),
    )
    skill = Tracker(env.spec.action_manifest("drift"), rows=5, infer_s=0.0)
    runner = SimRunner(env=env, scene=scene, skill=skill)
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        runner.run(max_ticks=HOLD_STEPS + 2)
    finally:
        runner.deactivate()
        skill.shutdown()
    assert runner.executor is not None
    # Two ticks awaiting the first chunk; every row after that runs two ticks late.
    assert runner.executor.stats.stale_rows == HOLD_STEPS - 2
    tick_indexed = _evaluate(VirtualLatency(ticks=2), rows=5, infer_s=0.0, n_episodes=1, speeds=(0.0, 0.0))
    assert tick_indexed.executor is not None
    assert tick_indexed.executor.stats.stale_rows == 0


def test_an_episode_and_a_report_written_before_real_time_still_load() -> None:
    old = {"episode_idx": 0, "seed": 3, "success": True, "steps": 4, "timing": {"step_ms_mean": 1.0}}
    episode = EpisodeResult.model_validate(old)
    assert episode.real_time is None
    assert "real_time" not in summarize([episode])


def test_the_summary_pools_the_episodes_real_time_figures() -> None:
    def episode(seed: int, stats: RealTimeStats) -> EpisodeResult:
        return EpisodeResult(episode_idx=seed, seed=seed, success=True, steps=10, real_time=stats)

    a = RealTimeStats.of(policy_ticks=6, held_slots=4, fresh_ticks=5, held_ticks=1, stale_ticks=0, wall_s=0.2)
    b = RealTimeStats.of(policy_ticks=10, held_slots=0, fresh_ticks=8, held_ticks=0, stale_ticks=2, wall_s=0.2)
    assert a.stale_or_held_ratio == pytest.approx(0.5)
    assert a.commands_per_s == pytest.approx(25.0)
    live = summarize([episode(0, a), episode(1, b)])["real_time"]
    assert live["stale_or_held_ratio"] == pytest.approx(7 / 20)
    assert live["held_ratio"] == pytest.approx(5 / 20)
    assert live["stale_ratio"] == pytest.approx(2 / 20)
    assert live["commands_per_s"] == pytest.approx(15 / 0.4)
    assert live["steps_per_s"] == pytest.approx(20 / 0.4)
    assert live["held_slots"] == 4


@pytest.mark.slow
def test_real_time_scores_what_the_virtual_delay_it_measured_scores_and_a_faster_policy_scores_more() -> None:
    n = 30
    # 2.5 slots of inference: the chunk is taken on the third tick after its request, whatever the jitter.
    slow = _evaluate("measured", rows=5, infer_s=2.5 * PERIOD_S, n_episodes=n)
    fast = _evaluate("measured", rows=5, infer_s=0.5 * PERIOD_S, n_episodes=n)
    assert slow.executor is not None
    assert fast.executor is not None
    slow_delay = median(slow.executor.stats.delays_ticks)
    assert slow_delay == 3
    assert median(fast.executor.stats.delays_ticks) <= 2
    virtual = _rate(_evaluate(VirtualLatency(ticks=int(slow_delay)), rows=5, infer_s=0.0, n_episodes=n))
    low, high = wilson_interval(*virtual)
    slow_rate = _rate(slow)[0] / n
    assert low <= slow_rate <= high, (slow_rate, virtual)
    assert _rate(fast)[0] / n > high
    for episode in slow.episode_results:
        assert episode.real_time is not None
        assert episode.real_time.held_ticks > 0  # the 3-tick delay starves two ticks of each chunk


def test_a_scene_file_asks_for_real_time_by_name_and_a_misspelt_mode_is_refused(tmp_path: Path) -> None:
    scene = tmp_path / "scene.yaml"
    base = "name: s\nenv: mock\ntask: t\nmax_steps: 5\n"
    scene.write_text(base + "virtual_latency: measured\n")
    assert SimEnvironment.from_yaml(scene).timing == "measured"
    assert SimEnvironment.from_yaml(scene).simulated_latency is None
    scene.write_text(base + "virtual_latency: null\n")
    assert SimEnvironment.from_yaml(scene).timing == "real"
    scene.write_text(base)
    assert SimEnvironment.from_yaml(scene).timing == "virtual"
    scene.write_text(base + "virtual_latency: measure\n")
    with pytest.raises(ROSConfigError, match=r"virtual_latency: Input should be an object or .* 'measured'"):
        SimEnvironment.from_yaml(scene)
