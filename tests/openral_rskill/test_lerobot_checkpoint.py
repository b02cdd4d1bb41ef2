"""A LeRobot checkpoint folder read without LeRobot: refusals, features, and the observation mapping."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from openral_core import FrameEncoding, JointState, PrivilegedState, ROSConfigError, SensorFrame, WorldState
from openral_hal.lerobot.units import UnitConversion
from openral_hal.manifests import load_robot_manifest
from openral_rskill.lerobot.checkpoint import REQUIRED_FILES, Checkpoint
from openral_rskill.lerobot.observation import ObservationMap
from openral_rskill.lerobot_policy import LeRobotPolicySkill

SO101 = load_robot_manifest("so101_follower")


def checkpoint(tmp_path: Path, **config: Any) -> Path:
    """A folder laid out as lerobot-train writes one (weights and statistics as placeholders)."""
    folder = tmp_path / "pretrained_model"
    folder.mkdir(exist_ok=True)
    base: dict[str, Any] = {
        "type": "act",
        "n_obs_steps": 1,
        "input_features": {
            "observation.state": {"type": "STATE", "shape": [6]},
            "observation.images.front": {"type": "VISUAL", "shape": [3, 48, 64]},
        },
        "output_features": {"action": {"type": "ACTION", "shape": [6]}},
        "chunk_size": 20,
        "n_action_steps": 10,
        "device": "cuda",
    }
    base.update(config)
    for name in REQUIRED_FILES:
        (folder / name).write_text("{}")
    (folder / "config.json").write_text(json.dumps(base))
    return folder


def test_a_checkpoint_says_what_it_reads_and_how_many_rows_it_predicts(tmp_path: Path) -> None:
    read = Checkpoint.read(str(checkpoint(tmp_path)))
    assert read.policy_type == "act"
    assert read.cameras == ["front"]
    assert (read.chunk_size, read.n_action_steps, read.observation_steps) == (20, 10, 1)
    diffusion = Checkpoint.read(str(checkpoint(tmp_path, type="diffusion", n_obs_steps=2, n_action_steps=8)))
    assert (diffusion.chunk_size, diffusion.observation_steps) == (8, 2)  # the executed window of the horizon


def test_a_policy_chunks_by_what_its_configuration_declares_whatever_its_type(tmp_path: Path) -> None:
    plugin = LeRobotPolicySkill.from_config(
        {"path": str(checkpoint(tmp_path, type="act_from_a_plugin"))}, robot=SO101, rate_hz=30
    )
    assert (plugin.checkpoint.chunk_size, plugin.info.chunk_size) == (20, 10)  # runs behind the chunk executor
    assert plugin.serves_many_episodes()
    no_chunk = {"type": "vqbet", "chunk_size": None, "n_action_steps": 5}
    stepping = LeRobotPolicySkill.from_config({"path": str(checkpoint(tmp_path, **no_chunk))}, robot=SO101, rate_hz=30)
    assert (stepping.checkpoint.chunk_size, stepping.info.chunk_size) == (1, 1)  # select_action, tick by tick
    assert not stepping.serves_many_episodes()


def test_a_hub_id_is_refused_saying_how_to_download_it() -> None:
    with pytest.raises(ROSConfigError, match=r"params\.path: 'lerobot/act_aloha' .*Hub id.*huggingface-cli download"):
        Checkpoint.read("lerobot/act_aloha")


@pytest.mark.parametrize("missing", REQUIRED_FILES)
def test_a_folder_missing_a_file_is_refused_naming_it(tmp_path: Path, missing: str) -> None:
    folder = checkpoint(tmp_path)
    (folder / missing).unlink()
    with pytest.raises(ROSConfigError, match=f"not a LeRobot checkpoint: it has no {missing}"):
        Checkpoint.read(str(folder))


def test_a_file_or_missing_folder_is_refused(tmp_path: Path) -> None:
    (tmp_path / "model.pt").write_bytes(b"x")
    for value in (str(tmp_path / "model.pt"), str(tmp_path / "nowhere"), str(tmp_path / ("m" * 300))):
        with pytest.raises(ROSConfigError, match="is not a folder"):
            Checkpoint.read(value)


def test_a_feature_openral_cannot_supply_is_a_config_error_naming_it(tmp_path: Path) -> None:
    folder = checkpoint(
        tmp_path,
        input_features={
            "observation.state": {"type": "STATE", "shape": [6]},
            "observation.tactile": {"type": "ENV", "shape": [12]},
        },
    )
    with pytest.raises(ROSConfigError, match=r"observation\.tactile.*cannot supply"):
        LeRobotPolicySkill.from_config({"path": str(folder)}, robot=SO101, rate_hz=30)


def test_an_action_of_another_size_than_the_robot_is_refused(tmp_path: Path) -> None:
    folder = checkpoint(tmp_path, output_features={"action": {"type": "ACTION", "shape": [14]}})
    with pytest.raises(ROSConfigError, match="acts on 14 dimensions but 'so101_follower' has 6"):
        LeRobotPolicySkill.from_config({"path": str(folder)}, robot=SO101, rate_hz=30)


def test_a_camera_map_naming_no_policy_camera_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match=r"params\.cameras: the policy reads no camera \['wrist'\]"):
        LeRobotPolicySkill.from_config(
            {"path": str(checkpoint(tmp_path)), "cameras": {"wrist": "cam1"}}, robot=SO101, rate_hz=30
        )


def test_the_skill_is_built_without_torch_and_says_what_it_reads(tmp_path: Path) -> None:
    skill = LeRobotPolicySkill.from_config(
        {"path": str(checkpoint(tmp_path)), "cameras": {"front": "top"}}, robot=SO101, rate_hz=30
    )
    assert skill.info.chunk_size == 10  # n_action_steps of the 20 predicted
    assert skill.info.observation == ["joint_state", "images.top", "task"]
    with pytest.raises(ROSConfigError, match=r"params\.rows: the policy predicts 20 rows"):
        LeRobotPolicySkill.from_config({"path": str(checkpoint(tmp_path)), "rows": 21}, robot=SO101, rate_hz=30)


def _world(bgr: np.ndarray, positions: list[float], names: list[str]) -> WorldState:
    frame = SensorFrame(
        sensor_id="front", stamp_ns=1, width=bgr.shape[1], height=bgr.shape[0], encoding=FrameEncoding.BGR8, data=bgr
    )
    return WorldState(
        stamp_ns=1,
        joint_state=JointState(names=names, positions=positions),
        image_frames={"front": frame},
        privileged=PrivilegedState(values={"environment_state": [0.1, 0.2, 0.3]}),
    )


def test_images_become_rgb_chw_floats_resized_and_joints_follow_the_manifest(tmp_path: Path) -> None:
    read = Checkpoint.read(str(checkpoint(tmp_path)))
    mapping = ObservationMap(read, robot=SO101, units=UnitConversion(SO101, "radians"))
    bgr = np.zeros((96, 128, 3), dtype=np.uint8)
    bgr[..., 2] = 255  # red in BGR
    names = SO101.joint_names
    arrays = mapping.arrays(_world(bgr, [0.1 * i for i in range(6)], list(reversed(names))))
    image = arrays["observation.images.front"]
    assert image.shape == (3, 48, 64)
    assert image.dtype == np.float32
    assert np.allclose(image[0], 1.0)  # the red channel comes first
    assert np.allclose(image[1:], 0.0)
    state = arrays["observation.state"]
    assert state.dtype == np.float32
    assert state.tolist() == pytest.approx([0.1 * i for i in reversed(range(6))])  # reordered to the manifest's


def test_a_missing_camera_or_a_state_of_another_size_is_named_at_the_step(tmp_path: Path) -> None:
    read = Checkpoint.read(str(checkpoint(tmp_path)))
    mapping = ObservationMap(read, robot=SO101, units=UnitConversion(SO101, "radians"))
    world = _world(np.zeros((48, 64, 3), np.uint8), [0.0] * 14, [f"s{i}" for i in range(14)])
    with pytest.raises(ValueError, match=r"observation\.state has 14 values here; the policy was trained on 6"):
        mapping.arrays(world)
    six = _world(np.zeros((48, 64, 3), np.uint8), [0.0] * 6, SO101.joint_names)
    no_camera = six.model_copy(update={"image_frames": {}})
    with pytest.raises(ValueError, match="needs a frame of camera 'front'"):
        mapping.arrays(no_camera)


def test_lerobot_degrees_and_range_conventions_round_trip() -> None:
    positions = np.array([0.5, -0.3, 1.0, 0.0, -1.2, 0.4])
    for units in ("degrees", "range"):
        convert = UnitConversion(SO101, units)
        there = convert.to_policy(positions)
        assert np.allclose(convert.to_radians(there[None, :]), positions[None, :])
    degrees = UnitConversion(SO101, "degrees").to_policy(positions)
    assert degrees[0] == pytest.approx(np.degrees(0.5))
    jaw = SO101.joints[-1]
    assert UnitConversion(SO101, "degrees").to_policy(np.array([0, 0, 0, 0, 0, jaw.lower]))[-1] == 0.0
    assert UnitConversion(SO101, "range").to_policy(np.array([0, 0, 0, 0, 0, jaw.upper]))[-1] == pytest.approx(100.0)


def test_a_deployment_without_the_policys_camera_is_refused_when_built(tmp_path: Path) -> None:
    from openral_core import RobotEnvironment  # noqa: PLC0415
    from openral_runner.factory import build_runner  # noqa: PLC0415

    folder = checkpoint(tmp_path)
    env = RobotEnvironment.model_validate(
        {
            "hal": {"robot_id": "so101_follower", "adapter": "null"},
            "vla": {"id": "lerobot_policy", "params": {"path": str(folder)}},
            "safety": {"client": "envelope"},
        }
    )
    with pytest.raises(ROSConfigError, match=r"sensors: skill 'lerobot_policy' reads camera\(s\) \['front'\]"):
        build_runner(env)


def test_configure_refuses_as_a_config_error_saying_what_is_needed(tmp_path: Path) -> None:
    from openral_core import ROSSkillError  # noqa: PLC0415

    skill = LeRobotPolicySkill.from_config({"path": str(checkpoint(tmp_path))}, robot=SO101, rate_hz=30)
    with pytest.raises(ROSSkillError) as caught:
        skill.configure()
    cause = caught.value.__cause__
    assert isinstance(cause, ROSConfigError)
    if sys.version_info < (3, 12):  # the extra installs nothing here: say which Python it needs
        assert "uv sync --python 3.12 --extra lerobot" in str(cause)
    else:  # LeRobot is there, and the placeholder files are no checkpoint it can load
        assert "LeRobot cannot load" in str(cause)


def _validate(tmp_path: Path, folder: Path) -> tuple[int, str]:
    """``openral validate`` of a deployment running ``folder`` on an SO-101: its exit code and output."""
    from click.testing import CliRunner  # noqa: PLC0415

    from openral_cli.main import cli  # noqa: PLC0415

    config = tmp_path / "deploy.yaml"
    config.write_text(
        "hal: {robot_id: so101_follower, adapter: 'null'}\n"
        f"vla: {{id: lerobot_policy, params: {{path: {json.dumps(str(folder))}}}}}\n"
        "safety: {client: envelope}\n"
    )
    out = CliRunner().invoke(cli, ["validate", str(config)])
    return out.exit_code, out.output


@pytest.mark.parametrize(
    ("inputs", "says"),
    [
        ({"observation.state": {"type": "STATE", "shape": [14]}}, "observation.state has 14 values but robot "
         "'so101_follower' has 6 joints"),
        ({"observation.state": {"type": "STATE", "shape": [6]}, "observation.environment_state": {"type": "ENV",
          "shape": [3]}}, "reads observation.environment_state, which only a simulator gives"),
    ],
    ids=["state-size", "environment-state"],
)  # fmt: skip
def test_validate_refuses_on_a_robot_what_only_a_simulator_gives(
    tmp_path: Path, inputs: dict[str, Any], says: str
) -> None:
    code, output = _validate(tmp_path, checkpoint(tmp_path, input_features=inputs))
    assert code == 2, output
    (line,) = output.strip().splitlines()
    assert says in line, line


def test_a_simulators_state_vector_of_another_size_is_still_read_in_simulation(tmp_path: Path) -> None:
    folder = checkpoint(tmp_path, input_features={"observation.state": {"type": "STATE", "shape": [14]}})
    skill = LeRobotPolicySkill.from_config({"path": str(folder)}, robot=SO101, rate_hz=30)  # as a scene builds it
    assert skill.inputs.state is not None
    assert skill.inputs.state.shape == (14,)


def test_a_config_json_nested_too_deeply_is_a_config_error_naming_it(tmp_path: Path) -> None:
    folder = checkpoint(tmp_path)
    (folder / "config.json").write_text("[" * 100_000 + "]" * 100_000)
    code, output = _validate(tmp_path, folder)
    assert code == 2, output
    (line,) = output.strip().splitlines()
    assert f"{folder / 'config.json'} is nested too deeply" in line


def test_weights_that_do_not_cover_the_policy_are_named_shortly(tmp_path: Path) -> None:
    from openral_rskill.lerobot.checkpoint import weights_mismatch  # noqa: PLC0415

    read = Checkpoint.read(str(checkpoint(tmp_path)))
    missing = ", ".join(f'"model.layer{i}.weight"' for i in range(40))
    error = RuntimeError(  # as torch's load_state_dict and safetensors' load_model word a strict load's refusal
        f"Error(s) in loading state_dict for ACTPolicy:\n\tMissing key(s) in state_dict: {missing}. "
        '\n\tUnexpected key(s) in state_dict: "extra.bias". '
    )
    refused = weights_mismatch(read, error)
    assert refused is not None
    text = str(refused)
    assert text.startswith(f"params.path: {read.path / 'model.safetensors'} does not hold the weights")
    assert "missing tensors model.layer0.weight, model.layer1.weight, model.layer10.weight" in text
    assert "and 36 more" in text
    assert "unexpected tensors extra.bias" in text
    assert len(text) - len(str(read.path)) < 325  # short whatever the 40 names; the folder's path is the caller's
    assert weights_mismatch(read, RuntimeError("CUDA out of memory")) is None
