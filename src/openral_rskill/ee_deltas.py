"""End-effector deltas (a gamepad's or keyboard's ``delta_x/y/z`` and gripper action) to joint targets.

LeRobot's gamepad and ``keyboard_ee`` teleoperators give a direction for the gripper to move in
the robot's base frame, one unit per axis, and a gripper action (0 close, 1 stay, 2 open). A
joint-position follower needs joint targets, so each step moves the end-effector site by
``step_m`` per unit along the asked axes with damped least squares on the site's Jacobian,
from the manifest's own kinematic chain (the MJCF the twin and the envelope use; no MuJoCo at
run time), and moves the jaw towards its open or closed limit by ``gripper_step_rad``. Targets
stay within the joint limits, and no joint is asked to move faster than its velocity limit: near a
singularity the damping and that cap shorten the step (its direction kept) instead of throwing the arm.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Final

import numpy as np

from openral_core.robot import JointKind, RobotManifest
from openral_hal.kinematics import SiteChain, load_site_chain

AXES: Final = ("delta_x", "delta_y", "delta_z")
GRIPPER: Final = "gripper"
CLOSE, STAY, OPEN = 0, 1, 2
"""LeRobot's gripper actions (``GripperAction``)."""

_DAMPING: Final = 0.02
"""Damped-least-squares λ (metres): a step asking more than the arm can do near a singularity shrinks."""
_FINITE_DIFFERENCE_RAD: Final = 1e-5


class EndEffectorDeltas:
    """One step of end-effector motion, as joint targets of a robot with a kinematic chain.

    Args:
        robot: The follower; its manifest names the MJCF and the end-effector site.
        step_m: Metres the site moves per step for a unit delta on one axis.
        gripper_step_rad: Radians the jaw moves per step on an open or close action.
        rate_hz: Steps per second (each joint moves at most its velocity limit's worth per step).

    Raises:
        ROSConfigError: The manifest has no MJCF model with an end-effector site.
    """

    def __init__(self, robot: RobotManifest, *, step_m: float, gripper_step_rad: float, rate_hz: float) -> None:
        self.chain: SiteChain = load_site_chain(robot)
        self.step_m = step_m
        self.gripper_step_rad = gripper_step_rad
        self._lower = np.array([j.lower for j in robot.joints])
        self._upper = np.array([j.upper for j in robot.joints])
        jaws = [i for i, j in enumerate(robot.joints) if j.kind is JointKind.GRIPPER]
        self._jaw = jaws[0] if jaws else None
        self._arm = [i for i, j in enumerate(robot.joints) if j.kind is not JointKind.GRIPPER]
        self._max_step = np.array([robot.joints[i].velocity_limit / rate_hz for i in self._arm])

    def jacobian(self, row: np.ndarray) -> np.ndarray:
        """d(site position)/d(arm joints) at ``row`` (3 × arm joints), by central differences."""
        arm = len(self._arm)
        rows = np.tile(np.asarray(row, dtype=np.float64), (2 * arm, 1))
        rows[np.arange(arm), self._arm] += _FINITE_DIFFERENCE_RAD
        rows[arm + np.arange(arm), self._arm] -= _FINITE_DIFFERENCE_RAD
        sites = self.chain.positions(rows)
        jacobian: np.ndarray = ((sites[:arm] - sites[arm:]) / (2 * _FINITE_DIFFERENCE_RAD)).T
        return jacobian

    def step(self, row: np.ndarray, action: Mapping[str, float]) -> np.ndarray:
        """The joint targets one step on from ``row`` (the manifest's order, radians) for ``action``."""
        target = np.array(row, dtype=np.float64)
        move = self.step_m * np.array([float(action.get(axis, 0.0)) for axis in AXES])
        if np.any(move):
            jacobian = self.jacobian(target)
            damped = jacobian @ jacobian.T + _DAMPING**2 * np.eye(3)
            joints = jacobian.T @ np.linalg.solve(damped, move)
            joints *= min(1.0, float(np.min(self._max_step / np.maximum(np.abs(joints), 1e-12))))
            target[self._arm] += joints
        gripper = round(float(action.get(GRIPPER, STAY)))
        if self._jaw is not None and gripper != STAY:
            target[self._jaw] += self.gripper_step_rad if gripper == OPEN else -self.gripper_step_rad
        clipped: np.ndarray = np.clip(target, self._lower, self._upper)
        return clipped
