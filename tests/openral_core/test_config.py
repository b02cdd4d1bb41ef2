"""Loading deployment YAML: every failure is one ROSConfigError naming the field and the fix."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from openral_core import RobotEnvironment, ROSConfigError, SensorReaderBackend
from openral_core.config import apply_overrides, validate_model

MINIMAL = """\
hal:
  robot_id: so101_follower
vla:
  id: hello
"""


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "deploy.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def _load_error(tmp_path: Path, text: str) -> ROSConfigError:
    with pytest.raises(ROSConfigError) as info:
        RobotEnvironment.from_yaml(_write(tmp_path, text))
    return info.value


def test_minimal_file_loads(tmp_path: Path) -> None:
    env = RobotEnvironment.from_yaml(str(_write(tmp_path, MINIMAL + "sensors:\n  - sensor_id: front\n")))
    assert env.hal.robot_id == "so101_follower"
    assert env.sensors[0].sensor_id == "front"


def test_shipped_example_deployment_loads() -> None:
    path = Path(__file__).parents[2] / "deployments" / "so101_twin_hello.yaml"
    env = RobotEnvironment.from_yaml(path)
    assert env.vla.id == "hello"


def test_unknown_nested_key_names_the_field_lists_allowed_keys_and_suggests(tmp_path: Path) -> None:
    error = _load_error(tmp_path, MINIMAL + "sensors:\n  - sensor_id: front\n    fpss: 30\n")
    assert error.field == "sensors[0].fpss"
    text = str(error)
    assert text.startswith("sensors[0].fpss: unknown key 'fpss'")
    assert "allowed keys: backend, backend_params, encoding, fps, height" in text
    assert error.hint == "did you mean 'fps'?"
    assert "did you mean 'fps'?" in text
    assert "deploy.yaml" in text, "the message names the file"


def test_unknown_top_level_key(tmp_path: Path) -> None:
    error = _load_error(tmp_path, MINIMAL + "rate: 30\n")
    assert error.field == "rate"
    assert "deadline_overrun_policy" in str(error)
    assert error.hint == "did you mean 'rate_hz'?"


def test_unknown_key_in_a_block(tmp_path: Path) -> None:
    error = _load_error(tmp_path, MINIMAL + "safety:\n  mdoe: clamp\n")
    assert error.field == "safety.mdoe"
    assert "allowed keys: client, max_joint_speed_factor, mode, workspace_max, workspace_min" in str(error)
    assert error.hint == "did you mean 'mode'?"


def test_unknown_key_without_a_close_match_has_no_suggestion(tmp_path: Path) -> None:
    error = _load_error(tmp_path, MINIMAL + "zzzzzz: 1\n")
    assert error.hint is None
    assert "did you mean" not in str(error)


def test_missing_required_field_is_named(tmp_path: Path) -> None:
    error = _load_error(tmp_path, "vla:\n  id: hello\n")
    assert error.field == "hal"
    assert "is required but missing" in str(error)


def test_missing_nested_field_is_named(tmp_path: Path) -> None:
    error = _load_error(tmp_path, MINIMAL + "sensors:\n  - fps: 30\n")
    assert error.field == "sensors[0].sensor_id"


def test_wrong_enum_value_lists_the_choices(tmp_path: Path) -> None:
    error = _load_error(tmp_path, MINIMAL + "deadline_overrun_policy: explode\n")
    assert error.field == "deadline_overrun_policy"
    for choice in ("warn", "drop", "raise"):
        assert f"'{choice}'" in str(error)


def test_backend_is_any_plugin_id_and_a_malformed_one_is_named(tmp_path: Path) -> None:
    env = RobotEnvironment.from_yaml(_write(tmp_path, MINIMAL + "sensors:\n  - sensor_id: front\n    backend: v4l2\n"))
    assert env.sensors[0].backend == "v4l2", "checked against the plugin registry when built, not by an enum"
    error = _load_error(tmp_path, MINIMAL + "sensors:\n  - sensor_id: front\n    backend: 'v4l2 camera'\n")
    assert error.field == "sensors[0].backend"


def test_unknown_backend_is_named_with_the_registered_ones(tmp_path: Path) -> None:
    from openral_runner.factory import build_runner  # noqa: PLC0415

    env = RobotEnvironment.from_yaml(_write(tmp_path, MINIMAL + "sensors:\n  - sensor_id: front\n    backend: v4l2\n"))
    with pytest.raises(ROSConfigError) as info:
        build_runner(env.model_copy(update={"hal": env.hal.model_copy(update={"adapter": "null"})}))
    assert info.value.field == "sensors[0].backend"
    assert SensorReaderBackend.GSTREAMER.value in str(info.value)


def test_model_rule_message_loses_the_pydantic_prefix(tmp_path: Path) -> None:
    error = _load_error(tmp_path, MINIMAL + "sensors:\n  - sensor_id: front\n    publish_to_ros: true\n")
    assert error.field == "sensors[0]"
    assert "publish_to_ros is true but publish_topic is empty" in str(error)
    assert "Value error" not in str(error)


def test_several_errors_mention_the_others(tmp_path: Path) -> None:
    error = _load_error(tmp_path, "hal:\n  robot_id: so101\nrate_hz: -1\nlatency_budget_ms: -1\n")
    assert "also invalid:" in str(error)
    assert "latency_budget_ms" in str(error)


def test_bad_yaml(tmp_path: Path) -> None:
    error = _load_error(tmp_path, "hal: [unclosed\n")
    assert "is not valid YAML" in str(error)
    assert isinstance(error.__cause__, Exception)


@pytest.mark.parametrize("text", ["- a\n- b\n", "just text\n", ""])
def test_top_level_must_be_a_mapping(tmp_path: Path, text: str) -> None:
    assert "must hold a mapping at the top level" in str(_load_error(tmp_path, text))


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match="file not found") as info:
        RobotEnvironment.from_yaml(tmp_path / "nope.yaml")
    assert info.value.hint == "check the path"
    assert isinstance(info.value.__cause__, FileNotFoundError)


def test_unreadable_path(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match="is a directory, not a regular file"):
        RobotEnvironment.from_yaml(tmp_path)
    locked = tmp_path / "locked.yaml"
    locked.write_text("hal: {}\n")
    locked.chmod(0)
    if os.access(locked, os.R_OK):  # root reads anything
        return
    with pytest.raises(ROSConfigError, match="permission denied"):
        RobotEnvironment.from_yaml(locked)


def test_validate_model_without_a_file() -> None:
    with pytest.raises(ROSConfigError) as info:
        validate_model(RobotEnvironment, {"hal": {"robot_id": "r"}, "vla": {"id": "v", "parms": {}}})
    assert info.value.field == "vla.parms"
    assert "[in " not in str(info.value)
    assert info.value.hint == "did you mean 'params'?"


def test_overrides_set_nested_keys_as_yaml_values_and_leave_the_data_as_it_was() -> None:
    data = {"name": "s", "executor": {"seam": "replace"}, "virtual_latency": None}
    changed = apply_overrides(
        data, ["executor.indexing=stale_start", "virtual_latency.ticks=3", "rate_hz=null", "cameras=[]", "name=a=b"]
    )
    assert changed == {
        "name": "a=b",  # the value is everything after the first '='
        "executor": {"seam": "replace", "indexing": "stale_start"},
        "virtual_latency": {"ticks": 3},
        "rate_hz": None,
        "cameras": [],
    }
    assert data == {"name": "s", "executor": {"seam": "replace"}, "virtual_latency": None}


@pytest.mark.parametrize(
    ("assignment", "words"),
    [
        ("virtual_latency", "is not KEY=VALUE"),
        ("executor..seam=crossfade", "is not KEY=VALUE"),
        ("=3", "is not KEY=VALUE"),
        ("name.first=x", "name is 's', not a mapping"),
        ("executor={a: [", "--set 'executor={a: \\['"),
        ("executor={a: 1, a: 2}", "duplicate key"),
    ],
)
def test_a_malformed_override_is_refused_naming_the_option(assignment: str, words: str) -> None:
    with pytest.raises(ROSConfigError, match=words) as caught:
        apply_overrides({"name": "s"}, [assignment])
    assert caught.value.field == "--set"
