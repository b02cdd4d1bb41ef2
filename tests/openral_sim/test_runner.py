"""SimRunner on the mock reaching task: tick semantics, episode outcomes, safety and faults as on a robot."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest

from openral_core import (
    EpisodeResult,
    EpisodeSmoothness,
    ROSConfigError,
    ROSRuntimeError,
    SimCamera,
    SimEnvironment,
    StopReason,
    TickResult,
    WithheldReason,
    WorldState,
)
from openral_observability.observer import TickObserver
from openral_rskill.testing import ScriptedSkill
from openral_runner.testing import FakeClock
from openral_sim.build import SkillFailed, build_sim_runner, run_episodes
from openral_sim.env import SimObservation, SimStep
from openral_sim.envs.mock import MockParams, MockReachEnv
from openral_sim.runner import SimRunner


def _scene(**update: Any) -> SimEnvironment:
    values: dict[str, Any] = {
        "name": "reach",
        "env": "mock",
        "task": "reach the target",
        "success_key": "is_success",
        "max_steps": 40,
        "n_episodes": 3,
        "seed": 7,
    }
    values.update(update)
    return SimEnvironment(**values)


class TickLog(TickObserver):
    def __init__(self) -> None:
        self.ticks: list[TickResult] = []
        self.worlds: list[WorldState | None] = []
        self.boundaries: list[tuple[Any, ...]] = []

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        self.ticks.append(tick)
        self.worlds.append(world)

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        self.boundaries.append(("start", episode_idx, task))

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        self.boundaries.append(("end", episode_idx, success, keep))

    def close(self) -> None:
        return


def _run(runner: SimRunner, log: TickLog | None = None) -> Any:
    if log is not None:
        runner.observers.append(log)
    runner.skill.configure()
    runner.skill.activate()
    runner.activate()
    try:
        return runner.run(max_ticks=1000)
    finally:
        runner.deactivate()


def test_one_env_step_per_tick_and_episodes_derived_from_the_ticks() -> None:
    runner = build_sim_runner(_scene(), "mock_reach_expert")
    log = TickLog()
    result = _run(runner, log)

    assert result.stop_reason == StopReason.TERMINATED
    assert [e.episode_idx for e in runner.episode_results] == [0, 1, 2]
    assert all(e.success and e.ended_by == "success" for e in runner.episode_results)
    # Each episode: one reset tick (no step index, no action), then one tick per env step.
    for episode in runner.episode_results:
        ticks = [t for t in log.ticks if t.episode_idx == episode.episode_idx]
        assert ticks[0].step_idx is None
        assert not ticks[0].action_applied
        steps = ticks[1:]
        assert [t.step_idx for t in steps] == list(range(episode.steps))
        assert all(t.reward is not None and t.action_applied for t in steps)
        assert [t.terminated for t in steps] == [False] * (episode.steps - 1) + [True]
        assert episode.sum_reward == pytest.approx(sum(t.reward for t in steps if t.reward is not None))
        assert episode.steps_to_success == episode.steps
        assert episode.seed == 7 + episode.episode_idx
    assert log.boundaries == [
        ("start", 0, "reach the target"),
        ("end", 0, True, True),
        ("start", 1, "reach the target"),
        ("end", 1, True, True),
        ("start", 2, "reach the target"),
        ("end", 2, True, True),
    ]
    # The skill saw the observation of the step before (its world state carries privileged values).
    world = log.worlds[1]
    assert world is not None
    assert world.privileged is not None
    assert world.joint_state is not None
    assert world.joint_state.positions == world.privileged.get("position")


def test_same_seeds_give_identical_outcomes_however_the_episodes_are_sliced() -> None:
    whole = run_episodes(_scene(n_episodes=6), "random").episodes
    again = run_episodes(_scene(n_episodes=6), "random").episodes
    tail = run_episodes(_scene(n_episodes=6), "random", first_episode=4, n_episodes=2).episodes
    assert [e.outcome() for e in again] == [e.outcome() for e in whole]
    assert [e.outcome() for e in tail] == [e.outcome() for e in whole[4:]]
    # The random skill really is random across episodes (a constant would pass the equalities too).
    assert len({e.sum_reward for e in whole}) == len(whole)


def test_an_episode_ends_at_max_steps_when_nothing_else_ends_it() -> None:
    batch = run_episodes(_scene(max_steps=5, n_episodes=2), "zero")
    assert [(e.steps, e.success, e.ended_by) for e in batch.episodes] == [(5, False, "max_steps")] * 2
    assert len(batch.tick_ms) == 10  # step ticks only


def test_a_success_key_the_env_never_reports_is_a_configuration_error() -> None:
    with pytest.raises(ROSConfigError, match="never reported 'succeed'") as caught:
        run_episodes(_scene(success_key="succeed", max_steps=3), "zero")
    assert caught.value.field == "success_key"
    assert "is_success" in str(caught.value)


def test_actions_outside_the_action_space_are_clamped_and_non_finite_ones_withheld() -> None:
    env = MockReachEnv(MockParams())
    skill = ScriptedSkill(["dx", "dy"], actions=[[5.0, -3.0], [math.nan, 0.0], [0.5, 0.5]], hold=[0.0, 0.0])
    runner = SimRunner(env=env, scene=_scene(n_episodes=1, max_steps=3), skill=skill)
    log = TickLog()
    result = _run(runner, log)
    steps = [t for t in log.ticks if t.step_idx is not None]
    assert steps[0].requested_action == [5.0, -3.0]
    assert steps[0].sent_action == [1.0, -1.0]
    assert steps[1].withheld_reason == WithheldReason.SAFETY
    assert not steps[1].action_applied
    assert steps[1].safety_violations == ["finite"]
    assert steps[2].sent_action == [0.5, 0.5]
    assert result.safety_violations == 1
    # The withheld tick stepped the env with the hold action: the point did not move.
    seen = [w for t, w in zip(log.ticks, log.worlds, strict=True) if t.step_idx is not None]
    positions = [w.joint_state.positions for w in seen if w is not None and w.joint_state is not None]
    assert len(positions) == 3
    assert positions[0] != positions[1]  # the clamped action moved it
    assert positions[1] == positions[2]


def test_a_failing_skill_is_withheld_and_counted_and_the_run_stops_after_too_many() -> None:
    env = MockReachEnv(MockParams())
    skill = ScriptedSkill(["dx", "dy"], raise_on={i: RuntimeError("boom") for i in range(100)})
    runner = SimRunner(env=env, scene=_scene(n_episodes=1, max_steps=50), skill=skill, max_consecutive_failures=3)
    log = TickLog()
    result = _run(runner, log)
    assert result.stop_reason == StopReason.FAULTS
    steps = [t for t in log.ticks if t.step_idx is not None]
    assert [t.withheld_reason for t in steps] == [WithheldReason.SKILL_ERROR] * 3
    # The episode under way is closed as ended by the faults (not cut off by max_steps), and not kept.
    assert runner.episode_results == [
        EpisodeResult(
            episode_idx=0,
            seed=7,
            success=False,
            steps=3,
            sum_reward=runner.episode_results[0].sum_reward,
            max_reward=runner.episode_results[0].max_reward,
            ended_by="faults",
            timing=runner.episode_results[0].timing,
            control_hz=env.spec.control_hz,
            # Three held steps: the hold action reached the env each time, no seam, no motion.
            smoothness=EpisodeSmoothness(commands=3, seams=0, reversals_per_s=0.0),
        )
    ]
    assert log.boundaries[-1] == ("end", 0, False, False)
    # What failed is the skill's own error, with where it happened.
    assert runner.failure is not None
    assert "RuntimeError: boom" in runner.failure
    assert "in episode 0 (step 3)" in runner.failure


def test_a_skill_failing_every_step_is_an_error_with_its_message_not_a_0_percent_run() -> None:
    # The SO-101 expert needs privileged values the mock does not expose: every step fails.
    with pytest.raises(SkillFailed, match="no privileged value 'grasp_pos'") as caught:
        run_episodes(_scene(n_episodes=4, max_steps=60), "so101_pick_expert")
    assert isinstance(caught.value, ROSRuntimeError)  # a run-time error (exit 1), not a configuration one
    assert "so101_pick_expert" in str(caught.value)
    episodes = caught.value.batch.episodes
    assert [(e.episode_idx, e.success, e.ended_by) for e in episodes] == [(0, False, "faults")]
    assert episodes[0].steps < 60


def test_an_episode_cut_by_a_stop_request_ends_as_stopped_not_at_max_steps() -> None:
    runner = build_sim_runner(_scene(n_episodes=2, max_steps=40), "zero")

    class StopAtStep(TickLog):
        def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
            super().on_tick(tick, world)
            if tick.step_idx == 4:
                runner.request_stop(StopReason.SIGINT)

    result = _run(runner, StopAtStep())
    assert result.stop_reason == StopReason.SIGINT
    assert [(e.steps, e.ended_by) for e in runner.episode_results] == [(5, "stopped")]
    assert runner.failure is None


def test_cameras_are_rendered_into_the_world_state_each_step() -> None:
    runner = build_sim_runner(_scene(n_episodes=1, cameras=[SimCamera(name="top", width=32, height=24)]), "zero")
    log = TickLog()
    _run(runner, log)
    steps = [w for t, w in zip(log.ticks, log.worlds, strict=True) if t.step_idx is not None]
    frames = [w.image_frames["top"] for w in steps if w is not None and w.image_frames]
    assert len(frames) == len(steps) == 40
    assert all(f.width == 32 and f.height == 24 for f in frames)
    # A new frame every step: the one rendered after the previous step (the reset's for step 0).
    assert [f.seq for f in frames] == list(range(1, 41))
    assert np.asarray(frames[0].as_array()).std() > 0


class TimedEnv(MockReachEnv):
    """The mock task, its reset, step and camera render each taking scripted fake time."""

    def __init__(self, clock: FakeClock) -> None:
        super().__init__(MockParams())
        self.clock = clock

    def reset(self, seed: int) -> SimObservation:
        self.clock.advance(0.011)
        return super().reset(seed)

    def step(self, action: np.ndarray) -> SimStep:
        self.clock.advance(0.007)
        return super().step(action)

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        self.clock.advance(0.003)
        return super().render(camera, width, height)


def test_a_step_tick_times_its_phases_as_a_robot_tick_does() -> None:
    clock = FakeClock()
    skill = ScriptedSkill(["dx", "dy"], actions=[[0.1, 0.0]] * 3, on_step=lambda _i: clock.advance(0.005))
    scene = _scene(n_episodes=1, max_steps=3, cameras=[SimCamera(name="top", width=16, height=12)])
    runner = SimRunner(env=TimedEnv(clock), scene=scene, skill=skill, clock=clock)
    log = TickLog()
    _run(runner, log)
    reset, *steps = log.ticks
    # The reset tick resets the env and the skill; the first step senses its observation.
    assert reset.step_idx is None
    assert reset.hal_ms == pytest.approx(11.0)
    assert log.worlds[0] is None
    assert len(steps) == 3
    for tick in steps:
        # Sensing renders the camera on the last observation, before the skill is asked; stepping is the HAL's phase.
        assert (tick.sensors_ms, tick.inference_ms, tick.hal_ms) == pytest.approx((3.0, 5.0, 7.0))
        assert (tick.world_state_ms, tick.safety_ms) == pytest.approx((0.0, 0.0))
        assert tick.tick_ms == pytest.approx(15.0)


def test_paced_runs_keep_the_scene_rate_and_free_runs_do_not_wait() -> None:
    paced = build_sim_runner(_scene(n_episodes=1, max_steps=10, rate_hz=100.0), "zero")
    started = time.perf_counter()
    _run(paced)
    assert time.perf_counter() - started >= 10 / 100.0  # 11 ticks on a 10 ms schedule: a lower bound
    free = build_sim_runner(_scene(n_episodes=1, max_steps=10), "zero")
    assert free.free_running
    assert not paced.free_running
    result = _run(free)
    assert result.missed_slots == 0
    assert result.deadline_misses == 0


def test_an_unknown_environment_or_skill_names_the_field_and_the_choices() -> None:
    with pytest.raises(ROSConfigError, match="mock") as env_error:
        build_sim_runner(_scene(env="mokc"), "zero")
    assert env_error.value.field == "env"
    with pytest.raises(ROSConfigError) as skill_error:
        build_sim_runner(_scene(), "zeroo")
    assert skill_error.value.field == "--skill"
