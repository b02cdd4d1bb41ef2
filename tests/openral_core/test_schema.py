"""The deployment JSON Schema: valid draft 2020-12, and it agrees with the model on real documents."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from openral_core import RobotEnvironment
from openral_core.schema import robot_environment_schema, robot_environment_schema_json

EXAMPLE = Path(__file__).parents[2] / "deployments" / "so101_twin_hello.yaml"
FULL: dict[str, Any] = {
    "name": "two_cameras",
    "rate_hz": 100,
    "deadline_overrun_policy": "drop",
    "latency_budget_ms": 8.5,
    "observers": [{"id": "thumbnails", "params": {"rate_hz": 2}}],
    "hal": {"robot_id": "so101_follower", "adapter": "mujoco_twin", "params": {"realtime_factor": 1.0}},
    "vla": {"id": "hello", "accept_licenses": ["Apache-2.0"], "params": {"amplitude_rad": 0.2}},
    "task": {"instruction": "wave", "task_id": "t1"},
    "sensors": [
        {"sensor_id": "front", "backend": "gstreamer", "fps": 30, "width": 640, "height": 480},
        {
            "sensor_id": "wrist",
            "backend": "opencv_thread",
            "required": False,
            "max_age_ms": 250,
            "encoding": "mono8",
            "publish_to_ros": True,
            "publish_topic": "/wrist/image_raw",
            "backend_params": {"device": 0},
        },
    ],
    "safety": {
        "client": "envelope",
        "mode": "reject",
        "workspace_min": [-0.5, -0.5, 0.0],
        "workspace_max": [0.5, 0.5, 0.6],
    },
    "realtime": {"sched_fifo_priority": 80, "cpu_affinity": [2, 3], "switch_interval_s": 0.001, "lock_memory": True},
    "faults": {"max_consecutive_failures": 3},
}


@pytest.fixture(scope="module")
def validator() -> jsonschema.protocols.Validator:
    schema = robot_environment_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _errors(validator: jsonschema.protocols.Validator, document: Any) -> list[str]:
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(document)]


def test_schema_is_valid_draft_2020_12() -> None:
    schema = robot_environment_schema()
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["title"] == "RobotEnvironment"
    jsonschema.Draft202012Validator.check_schema(schema)


def test_schema_json_text_is_the_same_schema() -> None:
    text = robot_environment_schema_json()
    assert text.endswith("\n")
    assert json.loads(text) == robot_environment_schema()


@pytest.mark.parametrize("document", ["example", "full", "minimal"])
def test_documents_the_model_accepts_pass_the_schema(validator: jsonschema.protocols.Validator, document: str) -> None:
    data = {
        "example": lambda: yaml.safe_load(EXAMPLE.read_text(encoding="utf-8")),
        "full": lambda: FULL,
        "minimal": lambda: {"hal": {"robot_id": "r"}, "vla": {"id": "v"}},
    }[document]()
    RobotEnvironment.model_validate(data)
    assert _errors(validator, data) == []


def test_yaml_null_safety_client_passes_the_schema(validator: jsonschema.protocols.Validator) -> None:
    data = {"hal": {"robot_id": "r"}, "vla": {"id": "v"}, "safety": {"client": None}}
    assert RobotEnvironment.model_validate(data).safety.client == "null"
    assert _errors(validator, data) == [], (
        "SafetyConfig documents `client: null` and the model accepts it, but the schema says client is a string, "
        "so editors flag a valid deployment; give the field a json_schema_extra/WithJsonSchema allowing null"
    )


@pytest.mark.parametrize(
    ("patch", "where"),
    [
        ({"rate": 30}, ""),
        ({"sensors": [{"sensor_id": "front", "fpss": 30}]}, "sensors/0"),
        ({"safety": {"mdoe": "clamp"}}, "safety"),
        ({"hal": {"robot_id": "r", "adaptor": "x"}}, "hal"),
    ],
)
def test_unknown_keys_are_rejected(
    validator: jsonschema.protocols.Validator, patch: dict[str, Any], where: str
) -> None:
    data = {"hal": {"robot_id": "r"}, "vla": {"id": "v"}, **patch}
    errors = _errors(validator, data)
    assert len(errors) == 1
    assert errors[0].startswith(f"{where}: Additional properties are not allowed")


@pytest.mark.parametrize(
    "patch",
    [
        {"rate_hz": 0},
        {"rate_hz": 20_000},
        {"deadline_overrun_policy": "explode"},
        {"sensors": [{"sensor_id": "1front"}]},
        {"sensors": [{"sensor_id": "front", "backend": "v4l2 camera"}]},
        {"safety": {"workspace_min": [0, 0]}},
        {"realtime": {"sched_fifo_priority": 100}},
    ],
)
def test_schema_rejects_what_the_model_rejects(
    validator: jsonschema.protocols.Validator, patch: dict[str, Any]
) -> None:
    data = {"hal": {"robot_id": "r"}, "vla": {"id": "v"}, **patch}
    with pytest.raises(ValueError, match="validation error"):
        RobotEnvironment.model_validate(data)
    assert _errors(validator, data) != []


def test_required_blocks_are_required(validator: jsonschema.protocols.Validator) -> None:
    assert set(robot_environment_schema()["required"]) == {"hal", "vla"}
    assert _errors(validator, {"vla": {"id": "v"}}) == [": 'hal' is a required property"]


SCENES = Path(__file__).parents[2] / "scenes" / "sim"


def test_every_shipped_scene_passes_the_scene_schema_and_the_model() -> None:
    from openral_core import SimEnvironment  # noqa: PLC0415
    from openral_core.schema import sim_environment_schema  # noqa: PLC0415

    schema = sim_environment_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    scene_validator = jsonschema.Draft202012Validator(schema)
    scenes = sorted(SCENES.glob("*.yaml"))
    assert len(scenes) >= 4
    for path in scenes:
        document = yaml.safe_load(path.read_text(encoding="utf-8"))
        assert _errors(scene_validator, document) == [], path.name
        SimEnvironment.from_yaml(path)
    wrong = {**yaml.safe_load(scenes[0].read_text(encoding="utf-8")), "success_key": "done"}
    assert any(error.startswith("success_key") for error in _errors(scene_validator, wrong))
