"""HoldSkill: latches the first measured pose and commands it every step."""

from __future__ import annotations

from collections.abc import Callable
from importlib.metadata import entry_points

import pytest

from openral_core import ControlMode, RobotManifest, ROSConfigError, ROSSkillError, RSkillState, WorldState
from openral_rskill.noop import HoldSkill

MakeWorld = Callable[..., WorldState]
START = [0.1, -0.2, 0.3, -0.4, 0.5, 0.6]


def active(robot: RobotManifest) -> HoldSkill:
    skill = HoldSkill.from_config({}, robot=robot, rate_hz=30.0)
    skill.configure()
    skill.activate()
    return skill


def test_holds_the_first_pose_whatever_is_measured_later(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = active(robot)
    first = skill.step(make_world(robot.joint_names, START, stamp_ns=7))
    assert first.first == START
    assert first.joint_names == robot.joint_names
    assert first.control_mode is ControlMode.JOINT_POSITION
    assert first.skill_id == "noop"
    assert first.stamp_ns == 7
    for k in range(1, 20):
        action = skill.step(make_world(robot.joint_names, [k * 0.01] * 6, stamp_ns=7 + k))
        assert action.first == START
        assert action.stamp_ns == 7 + k
    assert skill.held_pose == START


def test_reset_and_reactivate_latch_again(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = active(robot)
    skill.step(make_world(robot.joint_names, START))
    other = [0.0] * 6
    skill.reset()
    assert skill.step(make_world(robot.joint_names, other)).first == other
    skill.deactivate()
    skill.activate()
    assert skill.held_pose is None
    assert skill.step(make_world(robot.joint_names, START)).first == START


def test_matches_joints_by_name_and_clamps_into_limits(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = active(robot)
    names = list(reversed(robot.joint_names))
    positions = list(reversed([2.5, 0.0, 0.0, 0.0, 0.0, -0.1]))
    assert skill.step(make_world(names, positions)).first == [1.9, 0.0, 0.0, 0.0, 0.0, 0.0]


def test_missing_joint_state_latches_an_error(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = active(robot)
    with pytest.raises(ROSSkillError, match="no joint_state"):
        skill.step(make_world(None))
    assert skill.state is RSkillState.ERROR


def test_takes_no_params(robot: RobotManifest) -> None:
    with pytest.raises(ROSConfigError, match="unknown key 'hold'"):
        HoldSkill.from_config({"hold": True}, robot=robot, rate_hz=30.0)


def test_registered_as_the_noop_plugin() -> None:
    (entry,) = entry_points(group="openral.skills", name="noop")
    assert entry.load() is HoldSkill
