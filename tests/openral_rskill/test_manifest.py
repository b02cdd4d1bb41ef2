"""rSkill manifests: validation, licence gating, robot compatibility, built-in manifests."""

from __future__ import annotations

from importlib.metadata import entry_points
from pathlib import Path

import pytest
import yaml

from openral_core import ControlMode, RobotManifest, ROSConfigError, ROSLicenseError
from openral_core.plugins import SKILLS_GROUP
from openral_rskill import OPEN_LICENSES, RSkillManifest, builtin_manifest, rSkill

BASE = {"name": "wave", "version": "1.2.0", "skill": "hello", "license": "Apache-2.0"}


def write(tmp_path: Path, **overrides: object) -> Path:
    path = tmp_path / "rskill.yaml"
    data = {**BASE, **overrides}
    path.write_text(yaml.safe_dump({k: v for k, v in data.items() if v is not None}), encoding="utf-8")
    return path


def test_loads_a_manifest_and_reports_it_as_skill_info(tmp_path: Path) -> None:
    path = write(tmp_path, control_mode="joint_velocity", chunk_size=8, robots=["so101"], params={"a": 1})
    manifest = RSkillManifest.from_yaml(path)
    assert manifest.skill == "hello"
    assert manifest.robots == ["so101"]
    assert manifest.source == str(path)
    info = manifest.to_info()
    assert (info.skill_id, info.name, info.version, info.license) == ("hello", "wave", "1.2.0", "Apache-2.0")
    assert info.control_mode is ControlMode.JOINT_VELOCITY
    assert info.chunk_size == 8
    assert rSkill is RSkillManifest


@pytest.mark.parametrize("license_id", ["Apache-2.0", "MIT", "BSD-3-Clause", "CC-BY-4.0", "mit", "apache-2.0"])
def test_open_licences_pass_by_default(tmp_path: Path, license_id: str) -> None:
    assert RSkillManifest.from_yaml(write(tmp_path, license=license_id)).license == license_id


@pytest.mark.parametrize("license_id", ["LicenseRef-Acme-Proprietary", "GPL-3.0-only", "CC-BY-NC-4.0"])
def test_other_licences_are_refused_by_default(tmp_path: Path, license_id: str) -> None:
    path = write(tmp_path, license=license_id)
    with pytest.raises(ROSLicenseError) as info:
        RSkillManifest.from_yaml(path)
    message = str(info.value)
    assert f"'{license_id}'" in message
    assert str(path) in message
    assert f"add '{license_id}' to vla.accept_licenses" in message
    assert isinstance(info.value, ROSConfigError), "a licence refusal is a configuration error (exit 2)"


def test_non_commercial_licence_is_called_out(tmp_path: Path) -> None:
    with pytest.raises(ROSLicenseError, match="forbids commercial use"):
        RSkillManifest.from_yaml(write(tmp_path, license="CC-BY-NC-SA-4.0"))
    with pytest.raises(ROSLicenseError) as info:
        RSkillManifest.from_yaml(write(tmp_path, license="GPL-3.0-only"))
    assert "forbids commercial use" not in str(info.value)


def test_explicitly_accepted_licence_passes(tmp_path: Path) -> None:
    path = write(tmp_path, license="CC-BY-NC-4.0")
    assert RSkillManifest.from_yaml(path, accept_licenses=["cc-by-nc-4.0"]).license == "CC-BY-NC-4.0"


def test_explicit_list_replaces_the_default_list(tmp_path: Path) -> None:
    path = write(tmp_path, license="MIT")
    with pytest.raises(ROSLicenseError, match=r"'MIT'.*is not listed"):
        RSkillManifest.from_yaml(path, accept_licenses=["Apache-2.0"])
    with pytest.raises(ROSLicenseError):
        RSkillManifest.from_yaml(path, accept_licenses=[])


def test_no_non_commercial_licence_is_open_by_default() -> None:
    assert not [lic for lic in OPEN_LICENSES if "NC" in lic.upper().split("-")]


def test_unknown_key_names_the_field_and_the_allowed_keys(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError) as info:
        RSkillManifest.from_yaml(write(tmp_path, licence="MIT"))
    assert info.value.field == "licence"
    message = str(info.value)
    assert "allowed keys:" in message
    assert "weights_uri" in message
    assert "did you mean 'license'" in message


def test_missing_licence_is_named(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError) as info:
        RSkillManifest.from_yaml(write(tmp_path, license=None))
    assert info.value.field == "license"
    assert not isinstance(info.value, ROSLicenseError)


@pytest.mark.parametrize(
    ("field", "value"),
    [("license", "MIT OR Apache-2.0"), ("skill", "Hello World"), ("chunk_size", 0), ("control_mode", "torque")],
)
def test_bad_values_are_named(tmp_path: Path, field: str, value: object) -> None:
    with pytest.raises(ROSConfigError) as info:
        RSkillManifest.from_yaml(write(tmp_path, **{field: value}))
    assert info.value.field == field


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match="file not found"):
        RSkillManifest.from_yaml(tmp_path / "absent.yaml")


def test_robot_compatibility(tmp_path: Path) -> None:
    anywhere = RSkillManifest.from_yaml(write(tmp_path))
    anywhere.check_compatible("franka")
    listed = RSkillManifest.from_yaml(write(tmp_path, robots=["so100", "so101"]))
    listed.check_compatible("so101")
    with pytest.raises(ROSConfigError) as info:
        listed.check_compatible("franka")
    assert "'franka'" in str(info.value)
    assert "so100, so101" in str(info.value)


def test_deployment_params_override_manifest_defaults(tmp_path: Path) -> None:
    manifest = RSkillManifest.from_yaml(write(tmp_path, params={"amplitude_rad": 0.1, "ramp_s": 2.0}))
    assert manifest.merged_params({"ramp_s": 0.5}) == {"amplitude_rad": 0.1, "ramp_s": 0.5}
    assert manifest.params == {"amplitude_rad": 0.1, "ramp_s": 2.0}


@pytest.mark.parametrize("name", ["hello", "noop"])
def test_builtin_manifests_load_and_build_their_skill(name: str, robot: RobotManifest) -> None:
    manifest = RSkillManifest.from_yaml(builtin_manifest(name))
    (entry,) = entry_points(group=SKILLS_GROUP, name=manifest.skill)
    skill = entry.load().from_config(manifest.params, robot=robot, rate_hz=30.0)
    assert skill.info.skill_id == manifest.skill
    assert skill.info.license == manifest.license


def test_unknown_builtin_manifest_lists_the_known_ones() -> None:
    with pytest.raises(ROSConfigError, match="built-in: hello, noop"):
        builtin_manifest("hullo")


@pytest.mark.parametrize("size", ["[0, 0]", "[-4, 640]", "[640, 1000000]"])
def test_a_detector_input_size_out_of_range_is_refused_naming_the_field(tmp_path: Path, size: str) -> None:
    path = tmp_path / "cube.rskill.yaml"
    path.write_text(
        "name: cube\nkind: detector\nlicense: Apache-2.0\n"
        f"detector: {{model: cube.onnx, labels: [cube], input_size: {size}}}\n",
        encoding="utf-8",
    )
    with pytest.raises(ROSConfigError, match=r"detector\.input_size"):
        RSkillManifest.from_yaml(path)
