"""NullHAL: echoes commands as measurements, validates its parameters, keeps the HAL contract."""

from __future__ import annotations

import pytest

from openral_core import (
    Action,
    ControlMode,
    JointSpec,
    RobotManifest,
    ROSConfigError,
    ROSHardwareError,
)
from openral_hal import HAL, load_robot_manifest
from openral_hal.null import NullHAL


def _hal(**params: object) -> NullHAL:
    return NullHAL(load_robot_manifest("so101_follower"), params)


def test_is_a_hal() -> None:
    assert isinstance(_hal(), HAL)


def test_read_state_before_connect_raises() -> None:
    hal = _hal()
    with pytest.raises(ROSHardwareError, match="not connected"):
        hal.read_state()
    with pytest.raises(ROSHardwareError, match="not connected"):
        hal.send_action(Action(joint_names=["gripper"], targets=[[0.1]]))


def test_echoes_the_last_command_clipped_into_limits() -> None:
    hal = _hal()
    hal.connect()
    hal.send_action(Action(joint_names=["elbow_flex", "shoulder_pan"], targets=[[0.5, 9.0]]))

    state = hal.read_state()

    pan = load_robot_manifest("so101_follower").joint("shoulder_pan")
    assert state.names == hal.joint_names
    assert state.position_of("elbow_flex") == 0.5
    assert state.position_of("shoulder_pan") == pan.upper
    assert state.position_of("wrist_roll") == 0.0
    assert state.stamp_ns > 0


def test_state_is_a_snapshot_not_a_view() -> None:
    hal = _hal()
    hal.connect()
    before = hal.read_state()
    hal.send_action(Action(joint_names=["elbow_flex"], targets=[[0.5]]))
    assert before.position_of("elbow_flex") == 0.0


def test_initial_positions_param_and_default_clipping() -> None:
    manifest = RobotManifest(
        robot_id="offset",
        joints=[
            JointSpec(name="a", lower=0.2, upper=1.0, velocity_limit=1.0),
            JointSpec(name="b", lower=-1.0, upper=1.0, velocity_limit=1.0),
        ],
    )
    hal = NullHAL(manifest, {"initial_positions": {"b": -0.5}})
    hal.connect()
    assert hal.read_state().positions == [0.2, -0.5]


def test_unknown_param_names_the_key_and_the_allowed_ones() -> None:
    with pytest.raises(ROSConfigError) as info:
        _hal(inital_positions={})
    assert info.value.field == "hal.params.inital_positions"
    assert "allowed keys: initial_positions" in str(info.value)
    assert info.value.hint == "did you mean 'initial_positions'?"


def test_unknown_joint_and_wrong_mode_are_config_errors() -> None:
    hal = _hal()
    hal.connect()
    with pytest.raises(ROSConfigError, match="no joint 'elbow'"):
        hal.send_action(Action(joint_names=["elbow"], targets=[[0.1]]))
    with pytest.raises(ROSConfigError, match="ee_pose"):
        hal.send_action(Action(control_mode=ControlMode.EE_POSE, joint_names=["gripper"], targets=[[0.1]]))
    assert hal.read_state().positions == [0.0] * 6


def test_disconnect_is_idempotent_and_estop_keeps_state() -> None:
    hal = _hal()
    hal.disconnect()
    hal.connect()
    assert hal.is_connected
    hal.send_action(Action(joint_names=["gripper"], targets=[[0.3]]))
    hal.estop()
    assert hal.read_state().position_of("gripper") == 0.3
    hal.disconnect()
    hal.disconnect()
    assert not hal.is_connected
