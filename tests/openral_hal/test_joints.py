"""Matching actions and start positions to joints: the checks every adapter shares."""

from __future__ import annotations

import math

import pytest

from openral_core import (
    Action,
    ControlMode,
    JointKind,
    JointSpec,
    RobotManifest,
    ROSConfigError,
    ROSSafetyViolation,
)
from openral_hal.joints import JointIndex, initial_positions


def _manifest() -> RobotManifest:
    return RobotManifest(
        robot_id="arm",
        joints=[
            JointSpec(name="pan", lower=-1.0, upper=1.0, velocity_limit=1.0),
            JointSpec(name="lift", lower=0.2, upper=1.5, velocity_limit=1.0),
            JointSpec(name="jaw", kind=JointKind.GRIPPER, lower=-2.0, upper=-0.5, velocity_limit=1.0),
        ],
    )


def test_indices_follow_the_action_order_not_the_robot_order() -> None:
    index = JointIndex("arm", ["pan", "lift", "jaw"])
    assert index.indices(["jaw", "pan"]) == (2, 0)
    assert index.indices(["jaw", "pan"]) == (2, 0)  # answered from the cache
    assert index.indices(["lift"]) == (1,)


def test_unknown_joint_names_the_joint_and_suggests_the_closest() -> None:
    index = JointIndex("arm", ["pan", "lift", "jaw"])
    with pytest.raises(ROSConfigError) as info:
        index.indices(["pan", "lfit"])
    assert "'lfit'" in str(info.value)
    assert "pan, lift, jaw" in str(info.value)
    assert info.value.field == "action.joint_names"
    assert info.value.hint == "did you mean 'lift'?"


def test_cache_stays_bounded_and_correct() -> None:
    index = JointIndex("arm", [f"j{i}" for i in range(200)])
    for i in range(200):
        assert index.indices([f"j{i}"]) == (i,)
    assert len(index._cache) <= 64


def test_targets_rejects_non_finite_values() -> None:
    index = JointIndex("arm", ["pan", "lift"])
    with pytest.raises(ROSSafetyViolation) as info:
        index.targets(Action(joint_names=["pan", "lift"], targets=[[0.0, math.nan]]), adapter="test")
    assert info.value.check_name == "non_finite"
    assert "'lift'" in str(info.value)


def test_targets_rejects_other_control_modes() -> None:
    index = JointIndex("arm", ["pan"])
    action = Action(control_mode=ControlMode.JOINT_VELOCITY, joint_names=["pan"], targets=[[0.1]])
    with pytest.raises(ROSConfigError, match="joint_velocity"):
        index.targets(action, adapter="test")


def test_targets_uses_row_zero_of_a_chunk() -> None:
    index = JointIndex("arm", ["pan", "lift"])
    action = Action(joint_names=["lift", "pan"], targets=[[0.5, 0.1], [0.9, 0.9]])
    assert index.targets(action, adapter="test") == ((1, 0), [0.5, 0.1])


def test_initial_positions_default_to_zero_clipped_into_limits() -> None:
    assert initial_positions(_manifest(), {}) == [0.0, 0.2, -0.5]


def test_initial_positions_take_given_values() -> None:
    assert initial_positions(_manifest(), {"pan": 0.25, "jaw": -1.0}) == [0.25, 0.2, -1.0]


def test_initial_position_of_an_unknown_joint_is_a_config_error() -> None:
    with pytest.raises(ROSConfigError) as info:
        initial_positions(_manifest(), {"pna": 0.1})
    assert info.value.field == "hal.params.initial_positions.pna"
    assert info.value.hint == "did you mean 'pan'?"


@pytest.mark.parametrize("value", [1.2, math.nan])
def test_initial_position_outside_the_limits_is_a_config_error(value: float) -> None:
    with pytest.raises(ROSConfigError) as info:
        initial_positions(_manifest(), {"pan": value})
    assert info.value.field == "hal.params.initial_positions.pan"
