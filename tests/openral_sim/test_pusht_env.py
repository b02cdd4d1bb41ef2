"""The ``pusht`` environment adapter on gym-pusht's Push-T table."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from openral_core import ROSConfigError, SimCamera, SimEnvironment
from openral_sim.env import SimEnv
from openral_sim.envs.pusht import PushTEnv


def scene(**overrides: object) -> SimEnvironment:
    fields: dict[str, object] = {
        "name": "pusht",
        "env": "pusht",
        "env_id": "gym_pusht/PushT-v0",
        "task": "push the T onto the target",
        "max_steps": 300,
    }
    fields.update(overrides)
    return SimEnvironment.model_validate(fields)


@pytest.fixture(scope="module")
def env() -> Iterator[PushTEnv]:
    instance = PushTEnv.from_scene(scene(cameras=[SimCamera(name="top", width=96, height=96)]))
    yield instance
    instance.close()


def rollout(env: PushTEnv, seed: int, steps: int) -> list[list[float]]:
    """The full observations of an episode under seeded random targets."""
    rng = np.random.default_rng(2000 + seed)
    observations = [env.reset(seed).privileged["obs"]]
    for _ in range(steps):
        observations.append(env.step(rng.uniform(0.0, 512.0, size=2)).observation.privileged["obs"])
    return observations


def test_spec_describes_an_absolute_table_target(env: PushTEnv) -> None:
    assert isinstance(env, SimEnv)
    spec = env.spec
    assert spec.action_names == ("x", "y")
    assert spec.action_low == (0.0, 0.0)
    assert spec.action_high == (512.0, 512.0)
    assert spec.action_kind == "absolute"
    assert spec.control_hz == 10.0
    np.testing.assert_array_equal(spec.hold_action(np.array([100.0, 200.0])), [100.0, 200.0])


def test_observation_splits_the_state(env: PushTEnv) -> None:
    observation = env.reset(0)
    obs = observation.privileged["obs"]
    assert len(obs) == 5
    np.testing.assert_array_equal(observation.state, obs[:2])
    assert observation.privileged["environment_state"] == obs[2:]
    assert len(observation.privileged["environment_state"]) == len(env.spec.environment_state_names)
    assert observation.privileged["goal"] == pytest.approx([256.0, 256.0, np.pi / 4])
    assert observation.info["is_success"] is False


def test_the_disc_moves_to_the_target(env: PushTEnv) -> None:
    start = env.reset(0).state
    target = np.array([256.0, 60.0]) if start[1] > 256 else np.array([256.0, 450.0])
    for _ in range(10):
        state = env.step(target).observation.state
    assert np.linalg.norm(state - target) < np.linalg.norm(start - target) / 2


def test_reset_is_a_function_of_the_seed(env: PushTEnv) -> None:
    first = rollout(env, 3, 30)
    other = rollout(env, 4, 30)
    rollout(env, 17, 10)
    again = rollout(env, 3, 30)
    assert first[0] != other[0]
    assert first == again


def test_random_targets_do_not_succeed(env: PushTEnv) -> None:
    rng = np.random.default_rng(0)
    for seed in range(3):
        env.reset(seed)
        for _ in range(100):
            step = env.step(rng.uniform(0.0, 512.0, size=2))
            assert step.observation.info["is_success"] is False
            assert step.observation.info["coverage"] < 0.95
            assert not step.terminated
            assert not step.truncated


def test_camera_draws_the_table(env: PushTEnv) -> None:
    env.reset(0)
    frame = env.render("top", 96, 96)
    assert frame.shape == (96, 96, 3)
    assert frame.dtype == np.uint8
    assert frame.std() > 10
    wide = env.render("top", 64, 48)
    assert wide.shape == (48, 64, 3)
    env.reset(1)
    assert not np.array_equal(env.render("top", 96, 96), frame)


def test_unknown_camera_is_refused(env: PushTEnv) -> None:
    with pytest.raises(ROSConfigError, match="top") as info:
        PushTEnv.from_scene(scene(cameras=[SimCamera(name="front")]))
    assert info.value.field == "cameras"
    with pytest.raises(ROSConfigError):
        env.render("front", 32, 32)


def test_unknown_task_is_refused() -> None:
    with pytest.raises(ROSConfigError, match="gym_pusht/PushT-v0") as info:
        PushTEnv.from_scene(scene(env_id="gym_pusht/PushT-v1"))
    assert info.value.field == "env_id"


def test_unknown_env_kwarg_is_refused() -> None:
    with pytest.raises(ROSConfigError, match="obs_type"):
        PushTEnv.from_scene(scene(env_kwargs={"obs_type": "pixels"}))
