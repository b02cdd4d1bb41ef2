"""Joint units between openral (radians, the robot model's) and LeRobot's motor conventions.

LeRobot normalises each motor's reading with its calibration into one of three conventions
(``MotorNormMode``): ``degrees`` about the middle of the calibrated range (the SO-10x body's
default since lerobot 0.4.4), ``range_m100_100`` over the calibrated range (before), and
``range_0_100`` (a gripper: 0 closed). openral's manifests put each joint's zero at the middle
of its range and give the jaw in radians, so a conversion needs the joint's limits and
nothing else. The same conversion serves the ``lerobot_robot`` HAL (motor readings to radians
and back) and the ``lerobot_policy`` skill (radians to the policy's units and back), so a policy
recorded with ``lerobot-record`` sees on openral exactly the numbers it was trained on.

A checkpoint trained on openral recordings reads openral's own units: ``radians``, converting nothing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Final, Literal, get_args

import numpy as np

from openral_core import JointKind, RobotManifest
from openral_core.errors import ROSConfigError

JointUnits = Literal["radians", "degrees", "range"]
"""A whole arm's convention: radians, or LeRobot's degrees / -100..100 body with a 0..100 gripper."""

MotorNorm = Literal["radians", "degrees", "range_m100_100", "range_0_100"]
"""One joint's convention; the last three are LeRobot's ``MotorNormMode`` values."""

MOTOR_NORMS: Final = frozenset(get_args(MotorNorm))

RADIAN_BOUND: Final = 2 * math.pi + 0.5
"""No joint position in radians (an SO-101's jaw included) lies beyond this."""


def arm_norms(robot: RobotManifest, units: JointUnits) -> list[MotorNorm]:
    """Each joint's convention under a whole-arm one (a gripper is 0..100 unless in radians)."""
    bodies: dict[JointUnits, MotorNorm] = {"radians": "radians", "degrees": "degrees", "range": "range_m100_100"}
    body = bodies[units]
    return ["range_0_100" if units != "radians" and joint.kind is JointKind.GRIPPER else body for joint in robot.joints]


class UnitConversion:
    """Positions between the manifest's radians and per-joint LeRobot conventions, both ways.

    Args:
        robot: The joints, in the order of the values converted, with their limits.
        units: One convention for the whole arm, or one per joint.

    Raises:
        ROSConfigError: A per-joint list of another length than the robot's joints, or an unknown name.
    """

    def __init__(self, robot: RobotManifest, units: JointUnits | Sequence[MotorNorm]) -> None:
        norms = arm_norms(robot, units) if isinstance(units, str) else list(units)
        unknown = sorted(set(norms) - MOTOR_NORMS)
        if len(norms) != len(robot.joints) or unknown:
            raise ROSConfigError(
                f"'{robot.robot_id}' has {len(robot.joints)} joints; got conventions {norms}",
                field="joint_units",
                hint=f"one of {sorted(MOTOR_NORMS)} per joint",
            )
        self.norms: tuple[MotorNorm, ...] = tuple(norms)
        lower = np.array([j.lower for j in robot.joints], dtype=np.float64)
        upper = np.array([j.upper for j in robot.joints], dtype=np.float64)
        mode = np.array(self.norms)
        self._offset = np.zeros(len(norms))
        self._scale = np.ones(len(norms))
        degrees, signed, unsigned = mode == "degrees", mode == "range_m100_100", mode == "range_0_100"
        self._scale[degrees] = 180.0 / math.pi
        self._offset[signed] = ((lower + upper) / 2)[signed]
        self._scale[signed] = (200.0 / (upper - lower))[signed]
        self._offset[unsigned] = lower[unsigned]
        self._scale[unsigned] = (100.0 / (upper - lower))[unsigned]

    @property
    def identity(self) -> bool:
        """Every joint is in radians: nothing to convert."""
        return all(norm == "radians" for norm in self.norms)

    def to_policy(self, radians: np.ndarray) -> np.ndarray:
        """Positions in the manifest's radians (last axis: joints) in the conventions' units."""
        return (np.asarray(radians, dtype=np.float64) - self._offset) * self._scale

    def to_radians(self, values: np.ndarray) -> np.ndarray:
        """Values in the conventions' units (last axis: joints) back in radians."""
        return np.asarray(values, dtype=np.float64) / self._scale + self._offset


def plausible_units(bound: float) -> JointUnits:
    """The convention statistics whose largest magnitude is ``bound`` can be in: radians, or not."""
    return "radians" if bound <= RADIAN_BOUND else "degrees"


__all__ = [
    "MOTOR_NORMS",
    "RADIAN_BOUND",
    "JointUnits",
    "MotorNorm",
    "UnitConversion",
    "arm_norms",
    "plausible_units",
]
