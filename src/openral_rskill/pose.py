"""Reading a robot's measured pose out of a world state, by joint name."""

from __future__ import annotations

import math
from collections.abc import Sequence

from openral_core.errors import ROSSkillError
from openral_core.robot import RobotManifest
from openral_core.world import WorldState


def measured_pose(world_state: WorldState, joint_names: Sequence[str]) -> list[float]:
    """Positions of ``joint_names``, in that order, from ``world_state.joint_state``.

    The joint state may list its joints in any order and carry extra ones; matching is by name
    so a HAL that reports joints in a different order cannot scramble the pose.

    Raises:
        ROSSkillError: No joint state, a joint missing from it, or a non-finite position.
    """
    joint_state = world_state.joint_state
    if joint_state is None:
        raise ROSSkillError(
            "the world state has no joint_state, so there is no pose to start from "
            "(is the HAL's read_state wired into the world-state aggregator?)"
        )
    by_name = dict(zip(joint_state.names, joint_state.positions, strict=True))
    missing = [name for name in joint_names if name not in by_name]
    if missing:
        raise ROSSkillError(
            f"joint_state lacks joints {missing}; it reports {list(joint_state.names)} "
            "(the robot manifest and the HAL disagree on joint names)"
        )
    pose = [float(by_name[name]) for name in joint_names]
    bad = [name for name, value in zip(joint_names, pose, strict=True) if not math.isfinite(value)]
    if bad:
        raise ROSSkillError(f"joint_state has non-finite positions for {bad}")
    return pose


def clamp_to_limits(pose: Sequence[float], robot: RobotManifest) -> list[float]:
    """``pose`` (in manifest joint order) with each value clamped into its joint's ``[lower, upper]``."""
    return [min(max(value, spec.lower), spec.upper) for value, spec in zip(pose, robot.joints, strict=True)]
