"""Joint units between openral (radians, the robot model's) and LeRobot's conventions for SO-100/101 arms.

LeRobot's SO-101 follower reports ``<joint>.pos`` either in degrees (``use_degrees``, the default
since lerobot 0.4.4) or in -100..100 over the calibrated range (before), with the gripper always
0..100 (0 closed). Neither a checkpoint nor a dataset records which, so the deployment says it
(``joint_units``), and the policy's normalisation statistics are checked against it at configure.
A checkpoint trained on openral recordings (real or simulated) reads openral's own units:
``radians``, converting nothing.
"""

from __future__ import annotations

import math
from typing import Final, Literal

import numpy as np

from openral_core import JointKind, RobotManifest

JointUnits = Literal["radians", "degrees", "range"]

RADIAN_BOUND: Final = 2 * math.pi + 0.5
"""No joint position in radians (an SO-101's jaw included) lies beyond this."""


class UnitConversion:
    """State to the policy's units and the policy's actions back to radians, joint by joint.

    Args:
        robot: The joints, in the order of ``observation.state`` and ``action``, with their limits.
        units: The policy's convention.
    """

    def __init__(self, robot: RobotManifest, units: JointUnits) -> None:
        self.units = units
        lower = np.array([j.lower for j in robot.joints], dtype=np.float64)
        upper = np.array([j.upper for j in robot.joints], dtype=np.float64)
        gripper = np.array([j.kind is JointKind.GRIPPER for j in robot.joints])
        self._offset = np.zeros(len(robot.joints))
        self._scale = np.ones(len(robot.joints))
        if units == "degrees":
            self._scale[~gripper] = 180.0 / math.pi
        elif units == "range":
            middle = (lower + upper) / 2
            self._offset[~gripper] = middle[~gripper]
            self._scale[~gripper] = 200.0 / (upper - lower)[~gripper]
        if units != "radians":  # the jaw: 0 (closed, its lower limit) to 100 (open)
            self._offset[gripper] = lower[gripper]
            self._scale[gripper] = 100.0 / (upper - lower)[gripper]

    @property
    def identity(self) -> bool:
        return self.units == "radians"

    def to_policy(self, radians: np.ndarray) -> np.ndarray:
        """Measured positions (the manifest's order, radians) in the policy's units."""
        return (np.asarray(radians, dtype=np.float64) - self._offset) * self._scale

    def to_radians(self, values: np.ndarray) -> np.ndarray:
        """The policy's targets (rows × joints) back in radians."""
        return np.asarray(values, dtype=np.float64) / self._scale + self._offset


def plausible_units(bound: float) -> JointUnits:
    """The convention statistics whose largest magnitude is ``bound`` can be in: radians, or not."""
    return "radians" if bound <= RADIAN_BOUND else "degrees"


__all__ = ["RADIAN_BOUND", "JointUnits", "UnitConversion", "plausible_units"]
