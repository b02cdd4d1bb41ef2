"""Every built-in skill refuses hostile parameter values as a configuration error naming the field.

A deployment's ``vla.params`` (or ``--skill-params``) come from a user: a negative seed, a NaN
gain or a height of 10^308 must be an exit-2 error that names the field, never an unexpected
``ValueError`` from NumPy at start-up and never a skill that silently runs on nonsense.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from pydantic import BaseModel

from openral_cli.main import cli
from openral_core import RobotManifest, ROSConfigError
from openral_hal.manifests import load_robot_manifest
from openral_rskill.base import RSkillBase
from openral_rskill.gpu_passthrough import GpuPassthroughParams
from openral_rskill.hello import HelloParams
from openral_rskill.lerobot_policy import LeRobotPolicyParams
from openral_rskill.noop import HoldParams
from openral_rskill.onnx_policy import OnnxPolicyParams
from openral_runner.factory import SKILL_REGISTRY
from openral_sim.skills.aloha_experts import AlohaExpertParams
from openral_sim.skills.baselines import RandomParams, ZeroParams
from openral_sim.skills.libero_expert import LiberoExpertParams
from openral_sim.skills.metaworld_expert import MetaWorldExpertParams
from openral_sim.skills.mock_expert import MockExpertParams
from openral_sim.skills.so101_experts import PickParams, PickPlaceParams

REPO = Path(__file__).resolve().parents[2]

# skill id → (its params model, parameters that build it)
SKILLS: dict[str, tuple[type[BaseModel], dict[str, Any]]] = {
    "hello": (HelloParams, {}),
    "noop": (HoldParams, {}),
    "gpu_passthrough": (GpuPassthroughParams, {"device": "cpu"}),
    "onnx_policy": (OnnxPolicyParams, {"model": str(REPO / "models" / "so101_pick_mlp.onnx")}),
    "random": (RandomParams, {}),
    "zero": (ZeroParams, {}),
    "mock_reach_expert": (MockExpertParams, {}),
    "so101_pick_expert": (PickParams, {}),
    "so101_pickplace_expert": (PickPlaceParams, {}),
    "metaworld_expert": (MetaWorldExpertParams, {"task": "reach-v3"}),
    "aloha_transfer_cube_expert": (AlohaExpertParams, {}),
    "aloha_insertion_expert": (AlohaExpertParams, {}),
    "libero_expert": (LiberoExpertParams, {}),
    "lerobot_policy": (LeRobotPolicyParams, {"path": "<checkpoint>"}),  # a checkpoint folder, made per test
}

HOSTILE_NUMBERS: tuple[float | int, ...] = (-5, -(2**70), 2**70, 1e308, -1e308, math.nan, math.inf, -math.inf)


def _numeric_fields(model: type[BaseModel]) -> list[str]:
    names = []
    for name, field in model.model_fields.items():
        text = str(field.annotation)
        if "int" in text or "float" in text:
            names.append(name)
    return names


@pytest.fixture(scope="module")
def robot() -> RobotManifest:
    return load_robot_manifest("so101_follower")


def test_every_built_in_skill_is_swept() -> None:
    built_in = {
        name
        for name in SKILL_REGISTRY
        if SKILL_REGISTRY[name].__module__.startswith("openral_")
        and name not in ("remote_policy", "openpi_policy", "leader_arm", "lerobot_teleop")
    }
    # remote_policy and openpi_policy need a server to be built and their parameters are swept in their own
    # tests (tests/openral_remote); leader_arm needs a serial port; lerobot_teleop's parameters are LeRobot's
    # own config, decoded and checked by LeRobot (tests/openral_rskill/test_lerobot_teleop.py).
    assert built_in <= set(SKILLS), f"add these skills to the sweep: {sorted(built_in - set(SKILLS))}"


def _build(skill_id: str, params: dict[str, Any], robot: RobotManifest) -> RSkillBase:
    skill: RSkillBase = SKILL_REGISTRY[skill_id].from_config(params, robot=robot, rate_hz=30.0)
    return skill


def _lerobot_checkpoint(folder: Path) -> str:
    """A checkpoint folder as lerobot-train lays it out; building the skill reads only its JSON."""
    folder.mkdir()
    for name in ("model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json"):
        (folder / name).write_text("{}")
    config = {
        "type": "act",
        "input_features": {"observation.state": {"type": "STATE", "shape": [6]}},
        "output_features": {"action": {"type": "ACTION", "shape": [6]}},
        "chunk_size": 20,
        "n_action_steps": 10,
    }
    (folder / "config.json").write_text(json.dumps(config))
    return str(folder)


@pytest.mark.parametrize("skill_id", sorted(SKILLS))
def test_hostile_numbers_are_config_errors_naming_the_field(
    skill_id: str, robot: RobotManifest, tmp_path: Path
) -> None:
    model, base = SKILLS[skill_id]
    if base.get("path") == "<checkpoint>":
        base = {"path": _lerobot_checkpoint(tmp_path / "pretrained_model")}
    _build(skill_id, base, robot).shutdown()  # the base parameters are good
    for name in _numeric_fields(model):
        for value in HOSTILE_NUMBERS:
            params = {**base, name: value}
            try:
                skill = _build(skill_id, params, robot)
            except ROSConfigError as exc:
                refused = exc
            else:
                refused = None
            if refused is not None:
                assert refused.field is not None, (skill_id, name, refused)
                assert f"params.{name}" in refused.field, (skill_id, name, refused)
                continue
            # Accepted: it must be a finite value the skill can actually use.
            assert isinstance(value, int) or math.isfinite(value), f"{skill_id}.{name} accepted {value!r}"
            skill.shutdown()


def test_random_skill_refuses_a_negative_seed(robot: RobotManifest) -> None:
    with pytest.raises(ROSConfigError, match=r"vla\.params\.seed"):
        _build("random", {"seed": -5}, robot)


def test_skill_params_on_the_command_line_exit_2_naming_seed() -> None:
    result = CliRunner().invoke(
        cli,
        [
            "sim",
            "run",
            "--config",
            str(REPO / "scenes" / "sim" / "mock_reach.yaml"),
            "--skill",
            "random",
            "--skill-params",
            '{"seed": -5}',
            "--n-episodes",
            "1",
            "--no-cameras",
        ],
    )
    assert result.exit_code == 2, result.output
    assert "seed" in result.output
    assert "unexpected" not in result.output
