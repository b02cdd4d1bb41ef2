"""The ``metaworld`` environment adapter and the ``metaworld_expert`` skill on real MetaWorld tasks."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from openral_core import PrivilegedState, ROSConfigError, SimCamera, SimEnvironment, WorldState
from openral_sim.env import EndEffectorSensing, SimEnv, SimObservation
from openral_sim.envs.metaworld import MetaWorldEnv
from openral_sim.skills.metaworld_expert import MetaWorldExpert

TASK = "pick-place-v3"


def scene(**overrides: object) -> SimEnvironment:
    fields: dict[str, object] = {
        "name": "mw",
        "env": "metaworld",
        "env_id": TASK,
        "task": "pick and place",
        "success_key": "success",
        "max_steps": 200,
    }
    fields.update(overrides)
    return SimEnvironment.model_validate(fields)


@pytest.fixture(scope="module")
def env() -> Iterator[MetaWorldEnv]:
    instance = MetaWorldEnv.from_scene(scene())
    yield instance
    instance.close()


def rollout(env: MetaWorldEnv, seed: int, steps: int) -> list[np.ndarray]:
    """The full observations of an episode under seeded random actions."""
    rng = np.random.default_rng(1000 + seed)
    observations = [np.asarray(env.reset(seed).privileged["obs"])]
    for _ in range(steps):
        step = env.step(rng.uniform(-1.0, 1.0, size=4))
        observations.append(np.asarray(step.observation.privileged["obs"]))
    return observations


def run_expert(env: MetaWorldEnv, skill: MetaWorldExpert, seed: int, max_steps: int) -> int | None:
    """Steps the expert needed to succeed, or ``None``."""
    observation = env.reset(seed)
    skill.reset(seed=seed)
    for step_idx in range(1, max_steps + 1):
        world = WorldState(stamp_ns=step_idx, privileged=PrivilegedState(values=observation.privileged))
        action = skill.step(world)
        observation = env.step(np.asarray(action.first)).observation
        if observation.info["success"]:
            return step_idx
    return None


def test_spec_describes_the_sawyer_action_and_state(env: MetaWorldEnv) -> None:
    assert isinstance(env, SimEnv)
    spec = env.spec
    assert spec.action_names == ("dx", "dy", "dz", "grip")
    assert spec.action_low == (-1.0,) * 4
    assert spec.action_high == (1.0,) * 4
    assert spec.action_kind == "delta"
    assert spec.hold_dims == (3,)
    assert spec.control_hz == pytest.approx(80.0)
    np.testing.assert_array_equal(spec.hold_action(np.array([0.5, 0.5, 0.5, 0.7])), [0.0, 0.0, 0.0, 0.7])


def test_observation_splits_the_39_values(env: MetaWorldEnv) -> None:
    observation = env.reset(0)
    obs = np.asarray(observation.privileged["obs"])
    assert obs.shape == (39,)
    np.testing.assert_array_equal(observation.state, obs[:4])
    assert len(observation.state) == len(env.spec.state_names)
    environment_state = observation.privileged["environment_state"]
    assert len(environment_state) == len(env.spec.environment_state_names) == 17
    np.testing.assert_array_equal(environment_state[:14], obs[4:18])
    np.testing.assert_array_equal(environment_state[14:], obs[36:39])
    assert np.any(obs[36:39] != 0.0), "the goal must be observable (the experts steer to it)"


def test_success_is_reported_as_metaworld_gives_it(env: MetaWorldEnv) -> None:
    env.reset(0)
    step = env.step(np.zeros(4))
    assert isinstance(step.observation.info["success"], float)
    assert step.observation.info["success"] == 0.0
    assert not step.terminated
    assert not step.truncated


def test_reset_is_a_function_of_the_seed(env: MetaWorldEnv) -> None:
    first = rollout(env, 3, 20)
    other = rollout(env, 4, 20)
    rollout(env, 11, 5)
    again = rollout(env, 3, 20)
    assert not np.array_equal(first[0], other[0])
    for before, after in zip(first, again, strict=True):
        np.testing.assert_array_equal(before, after)


def test_a_fresh_instance_reproduces_an_episode(env: MetaWorldEnv) -> None:
    fresh = MetaWorldEnv(TASK)
    try:
        expected = rollout(env, 5, 10)
        for before, after in zip(expected, rollout(fresh, 5, 10), strict=True):
            np.testing.assert_array_equal(before, after)
    finally:
        fresh.close()


def test_steps_past_metaworlds_500_step_horizon(env: MetaWorldEnv) -> None:
    env.reset(0)
    for _ in range(505):
        step = env.step(np.zeros(4))
        assert not step.truncated
    assert isinstance(step.observation, SimObservation)


def test_weld_rows_keep_the_entries_metaworld_does_not_know(env: MetaWorldEnv) -> None:
    model = env._env.model
    assert model.eq_data.shape[1] >= 11
    np.testing.assert_array_equal(model.eq_data[0, :11], [0, 0, 0, 0, 0, 0, -1, 0, 0, 0, 5])


def test_expert_solves_pick_place(env: MetaWorldEnv) -> None:
    skill = MetaWorldExpert.from_config({"task": TASK}, robot=env.spec.action_manifest("sawyer"), rate_hz=80.0)
    skill.configure()
    skill.activate()
    steps = [run_expert(env, skill, seed, max_steps=200) for seed in range(3)]
    assert all(s is not None for s in steps), f"expert failed on some seeds: {steps}"


def test_expert_refuses_an_unknown_task(env: MetaWorldEnv) -> None:
    with pytest.raises(ROSConfigError, match="pick-place-v3") as info:
        MetaWorldExpert.from_config({"task": "pick-place-v2"}, robot=env.spec.action_manifest("sawyer"), rate_hz=80.0)
    assert info.value.field == "params.task"


def test_expert_needs_privileged_state(env: MetaWorldEnv) -> None:
    skill = MetaWorldExpert.from_config({"task": TASK}, robot=env.spec.action_manifest("sawyer"), rate_hz=80.0)
    skill.configure()
    skill.activate()
    skill.reset(seed=0)
    with pytest.raises(Exception, match="simulation"):
        skill.step(WorldState(stamp_ns=1))


@pytest.mark.parametrize("env_id", ["pick-place-v2", "pickplace-v3", "pick_place"])
def test_unknown_task_names_the_closest(env_id: str) -> None:
    with pytest.raises(ROSConfigError, match="pick-place-v3") as info:
        MetaWorldEnv.from_scene(scene(env_id=env_id))
    assert info.value.field == "env_id"


def test_missing_task_is_refused() -> None:
    with pytest.raises(ROSConfigError) as info:
        MetaWorldEnv.from_scene(scene(env_id=None))
    assert info.value.field == "env_id"


def test_unknown_camera_lists_the_models_cameras() -> None:
    with pytest.raises(ROSConfigError, match="corner2") as info:
        MetaWorldEnv.from_scene(scene(cameras=[SimCamera(name="front")]))
    assert info.value.field == "cameras"


def test_unknown_env_kwarg_is_refused() -> None:
    with pytest.raises(ROSConfigError, match="frame_skip"):
        MetaWorldEnv.from_scene(scene(env_kwargs={"frame_skip": 2}))


@pytest.mark.gl
def test_camera_renders_the_scene() -> None:
    env = MetaWorldEnv.from_scene(scene(cameras=[SimCamera(name="corner", width=96, height=64)]))
    try:
        env.reset(0)
        frame = env.render("corner", 96, 64)
        assert frame.shape == (64, 96, 3)
        assert frame.dtype == np.uint8
        assert frame.std() > 10
        env.reset(1)
        moved = env.render("corner", 96, 64)
        assert np.abs(moved.astype(int) - frame.astype(int)).sum() > 0, "a new episode's objects must show"
        assert env.render("topview", 32, 32).shape == (32, 32, 3)
    finally:
        env.close()


def test_the_end_effector_is_the_hand_position_the_state_reports(env: MetaWorldEnv) -> None:
    assert isinstance(env, EndEffectorSensing)
    positions = [env.reset(3).state[:3]]
    ends = [env.end_effector_positions()]
    for _ in range(5):
        positions.append(env.step(np.array([1.0, 0.0, 0.0, 0.0])).observation.state[:3])
        ends.append(env.end_effector_positions())
    np.testing.assert_allclose(ends, positions, atol=1e-6)
    assert ends[-1][0] - ends[0][0] > 0.01  # the hand moved along x
