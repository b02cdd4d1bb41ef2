"""The ``aloha`` environment adapter on gym-aloha's tasks, and the scripted ALOHA experts."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("gym_aloha", reason="needs the 'aloha' extra")

from openral_cli.main import cli
from openral_core import ROSConfigError, SimCamera, SimEnvironment
from openral_core.config import load_model_yaml
from openral_hal import load_robot_manifest
from openral_sim.build import run_episodes
from openral_sim.env import EndEffectorSensing, SimEnv
from openral_sim.envs.aloha import AlohaEnv

ROOT = Path(__file__).resolve().parents[2]
SCENES = ROOT / "scenes" / "sim"
TRANSFER, INSERTION = "AlohaTransferCube-v0", "AlohaInsertion-v0"
REST = np.array([0, -0.96, 1.16, 0, -0.3, 0, 1.0] * 2)


def scene(env_id: str = TRANSFER, **overrides: object) -> SimEnvironment:
    fields: dict[str, object] = {"name": "aloha", "env": "aloha", "env_id": env_id, "task": "t", "max_steps": 300}
    fields.update(overrides)
    return SimEnvironment.model_validate(fields)


@pytest.fixture(scope="module")
def env() -> Iterator[AlohaEnv]:
    instance = AlohaEnv.from_scene(scene())
    yield instance
    instance.close()


def rollout(env: AlohaEnv, seed: int, steps: int) -> list[list[float]]:
    """Every ``qpos`` of an episode under seeded random joint targets around the rest pose."""
    rng = np.random.default_rng(1000 + seed)
    qpos = [env.reset(seed).privileged["qpos"]]
    for _ in range(steps):
        qpos.append(env.step(REST + rng.normal(0, 0.2, 14)).observation.privileged["qpos"])
    return qpos


def test_the_action_space_is_the_bimanual_manifest(env: AlohaEnv) -> None:
    assert isinstance(env, SimEnv)
    manifest = load_robot_manifest("aloha_bimanual_viperx")
    spec = env.spec
    assert list(spec.action_names) == manifest.joint_names == list(spec.state_names)
    assert spec.action_low == tuple(j.lower for j in manifest.joints)
    assert spec.action_high == tuple(j.upper for j in manifest.joints)
    assert spec.action_kind == "absolute"
    assert spec.control_hz == 50.0
    assert spec.environment_state_names == ("cube_x", "cube_y", "cube_z", "cube_qw", "cube_qx", "cube_qy", "cube_qz")


def test_reset_and_steps_are_gym_alohas_own(env: AlohaEnv, monkeypatch: pytest.MonkeyPatch) -> None:
    import gymnasium as gym  # noqa: PLC0415
    from dm_control import mujoco as dm_mujoco  # noqa: PLC0415

    # gym-aloha renders three cameras every step; only its physics is compared here.
    blank = np.zeros((480, 640, 3), np.uint8)
    monkeypatch.setattr(dm_mujoco.Physics, "render", lambda *_args, **_kwargs: blank)
    reference = gym.make("gym_aloha/AlohaTransferCube-v0", obs_type="pixels_agent_pos")
    try:
        observation, _ = reference.reset(seed=11)
        ours = env.reset(11)
        np.testing.assert_array_equal(ours.state, observation["agent_pos"])
        physics = reference.unwrapped._env.physics
        np.testing.assert_array_equal(ours.privileged["environment_state"], physics.data.qpos[16:])
        rng = np.random.default_rng(5)
        for _ in range(10):
            action = REST + rng.normal(0, 0.1, 14)
            expected, reward, *_ = reference.step(action)
            step = env.step(action)
            np.testing.assert_array_equal(step.observation.state, expected["agent_pos"])
            assert step.reward == reward
    finally:
        reference.close()


def test_reset_is_a_function_of_the_seed(env: AlohaEnv) -> None:
    first = rollout(env, 3, 20)
    rollout(env, 4, 5)  # whatever ran before
    again = rollout(env, 3, 20)
    fresh = AlohaEnv.from_scene(scene())
    try:
        other_instance = rollout(fresh, 3, 20)
    finally:
        fresh.close()
    assert again == first == other_instance
    assert env.reset(3).privileged["environment_state"] != env.reset(4).privileged["environment_state"]


def test_steps_render_nothing_and_cameras_only_what_is_asked(env: AlohaEnv) -> None:
    rollout(env, 0, 3)
    assert env._views._renderers == {}  # no camera asked: no renderer exists
    frame = env.render("top", 320, 240)
    assert frame.shape == (240, 320, 3)
    assert frame.dtype == np.uint8
    assert frame.std() > 10  # the table, the arms and the cube, not a blank image
    assert list(env._views._renderers) == [("top", 320, 240)]


def test_diverging_physics_ends_the_episode_failed_and_the_next_reset_is_sound(env: AlohaEnv) -> None:
    env.reset(0)
    low, high = np.array(env.spec.action_low), np.array(env.spec.action_high)
    for k in range(200):
        step = env.step(high if k % 2 else low)
        if step.terminated:
            break
    assert step.terminated
    assert step.observation.info["is_success"] is False
    assert "physics_error" in step.observation.info
    assert np.isfinite(step.observation.state).all()
    assert rollout(env, 3, 5) == rollout(env, 3, 5)  # reset restores a sound, seeded state


def test_the_gripper_state_is_the_normalised_opening(env: AlohaEnv) -> None:
    env.reset(0)
    for _ in range(40):
        opened = env.step(np.r_[REST[:6], 1.0, REST[7:13], 0.0]).observation.state
    assert opened[6] > 0.9  # left commanded open
    assert opened[13] < 0.15  # right commanded closed


@pytest.mark.parametrize(
    ("env_id", "skill"), [(TRANSFER, "aloha_transfer_cube_expert"), (INSERTION, "aloha_insertion_expert")]
)
def test_the_expert_succeeds_and_the_random_baseline_does_not(env_id: str, skill: str) -> None:
    task = scene(env_id, n_episodes=2, seed=20)
    expert = run_episodes(task, skill).episodes
    assert [e.success for e in expert] == [True, True]
    assert all(e.steps_to_success is not None and e.steps_to_success < 300 for e in expert)
    baseline = run_episodes(task.model_copy(update={"max_steps": 100}), "random").episodes
    assert not any(e.success for e in baseline)


def test_the_expert_is_deterministic_per_seed() -> None:
    task = scene(n_episodes=1, seed=7)
    first = run_episodes(task, "aloha_transfer_cube_expert").episodes
    again = run_episodes(task, "aloha_transfer_cube_expert").episodes
    assert [e.outcome() for e in again] == [e.outcome() for e in first]


def test_the_shipped_scenes_load_and_film_the_top_camera() -> None:
    for name, env_id in (("aloha_transfer_cube.yaml", TRANSFER), ("aloha_insertion.yaml", INSERTION)):
        loaded = load_model_yaml(SimEnvironment, SCENES / name)
        assert loaded.env_id == env_id
        assert loaded.robot == "aloha_bimanual_viperx"
        assert [(c.name, c.width, c.height) for c in loaded.cameras] == [("top", 640, 480)]


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"env_id": "AlohaTransfer-v0"}, "env_id"),
        ({"env_id": None}, "env_id"),
        ({"cameras": [SimCamera(name="wrist", width=64, height=64)]}, "cameras"),
        ({"env_kwargs": {"render_every_step": True}}, "env_kwargs.render_every_step"),
    ],
)
def test_bad_scene_fields_are_refused_by_name(overrides: dict[str, object], field: str) -> None:
    with pytest.raises(ROSConfigError) as caught:
        AlohaEnv.from_scene(scene(**overrides))  # type: ignore[arg-type]
    assert caught.value.field == field


def test_an_unknown_task_exits_2_with_one_line_naming_the_field(tmp_path: Path) -> None:
    bad = tmp_path / "scene.yaml"
    bad.write_text((SCENES / "aloha_insertion.yaml").read_text().replace("AlohaInsertion-v0", "AlohaInsert-v0"))
    result = CliRunner().invoke(cli, ["sim", "run", "--config", str(bad), "--skill", "zero"])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output
    assert "env_id" in lines[0]
    assert "AlohaInsertion-v0" in lines[0]


def test_the_end_effectors_are_both_grippers_and_move_with_their_own_arm(env: AlohaEnv) -> None:
    assert isinstance(env, EndEffectorSensing)
    env.reset(0)
    env.step(REST)
    before = env.end_effector_positions()
    assert before.shape == (2, 3)
    assert before[0, 0] < 0 < before[1, 0]  # the left arm stands at negative x, the right at positive
    turned = REST.copy()
    turned[0] += 0.3  # the left arm's waist only
    for _ in range(10):
        env.step(turned)
    after = env.end_effector_positions()
    assert np.linalg.norm(after[0] - before[0]) > 0.02
    assert np.linalg.norm(after[1] - before[1]) < 0.005  # the right one only settles
