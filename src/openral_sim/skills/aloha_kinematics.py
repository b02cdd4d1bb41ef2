"""Joint-space motion for ALOHA's ViperX arms: inverse kinematics and timed gripper-pose keyframes.

The scripted ALOHA experts plan where each gripper should be, as keyframes in time, and turn
every interpolated pose into joint targets here. Commanding joints (rather than gym-aloha's
mocap-welded end-effector variant, whose weld no longer holds the gripper's orientation on
MuJoCo 3) keeps the plan valid on the MuJoCo the project locks.

Inverse kinematics is damped least squares on the 6-D pose error of a point fixed in the
gripper link, warm-started from the previous solution, on a private ``MjData`` so it never
touches the simulation. The position servos sag under gravity (their gains are low at the
wrist); adding the gravity torque divided by each servo's gain to its target cancels that.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

try:
    import mujoco
except ImportError as exc:  # pragma: no cover - the aloha extra installs MuJoCo
    from openral_core import ROSDependencyMissing

    raise ROSDependencyMissing("mujoco", extra="aloha", needed_for="the ALOHA experts") from exc

Side = Literal["left", "right"]
SIDES: tuple[Side, Side] = ("left", "right")
ARM_QPOS: dict[Side, np.ndarray] = {"left": np.arange(0, 6), "right": np.arange(8, 14)}
"""Each arm's six joints in the model's ``qpos`` (fingers follow at 6-7 and 14-15)."""
ROBOT_DOF = 16


def frame(x_axis: np.ndarray | list[float], y_hint: np.ndarray | list[float]) -> np.ndarray:
    """A rotation whose x axis is ``x_axis`` and whose y axis is ``y_hint`` made orthogonal to it."""
    x = np.asarray(x_axis, dtype=np.float64)
    x = x / np.linalg.norm(x)
    y = np.asarray(y_hint, dtype=np.float64)
    y = y - x * (x @ y)
    y = y / np.linalg.norm(y)
    return np.stack([x, y, np.cross(x, y)], axis=1)


@dataclass(frozen=True)
class Keyframe:
    """Where a gripper point should be at step ``t``: position, orientation, opening (0 closed, 1 open)."""

    t: int
    position: np.ndarray
    rotation: np.ndarray
    opening: float


def _rotation_towards(r0: np.ndarray, r1: np.ndarray, fraction: float) -> np.ndarray:
    """The rotation ``fraction`` of the way from ``r0`` to ``r1`` along the shortest arc."""
    relative = r0.T @ r1
    angle = float(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1.0, 1.0)))
    if angle < 1e-8:
        return r1.copy()
    axis = np.array(
        [relative[2, 1] - relative[1, 2], relative[0, 2] - relative[2, 0], relative[1, 0] - relative[0, 1]]
    ) / (2 * np.sin(angle))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    step = np.eye(3) + np.sin(fraction * angle) * k + (1 - np.cos(fraction * angle)) * (k @ k)
    return np.asarray(r0 @ step)


def sample(keys: list[Keyframe], t: int) -> Keyframe:
    """The pose at step ``t``: smooth-step between the surrounding keyframes, the last one after the end."""
    for start, end in itertools.pairwise(keys):
        if start.t <= t <= end.t:
            a = (t - start.t) / max(end.t - start.t, 1)
            a = a * a * (3 - 2 * a)
            return Keyframe(
                t,
                start.position + a * (end.position - start.position),
                _rotation_towards(start.rotation, end.rotation, a),
                start.opening + a * (end.opening - start.opening),
            )
    return keys[-1]


class ViperXKinematics:
    """Gripper poses and inverse kinematics of both arms of one ALOHA model."""

    def __init__(self, model: Any, *, iterations: int = 60, damping: float = 1e-2) -> None:
        self.model = model
        self.data = mujoco.MjData(model)
        self.iterations = iterations
        self.damping = damping
        self.body = {side: model.body(f"vx300s_{side}/gripper_link").id for side in SIDES}
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))
        gains = np.asarray(model.actuator_gainprm[:ROBOT_DOF, 0], dtype=np.float64)
        self._gains = np.where(gains > 0, gains, 1.0)

    def gripper_pose(self, qpos: np.ndarray, side: Side) -> tuple[np.ndarray, np.ndarray]:
        """Position and rotation of ``side``'s gripper link at ``qpos``."""
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        body = self.body[side]
        return self.data.xpos[body].copy(), self.data.xmat[body].reshape(3, 3).copy()

    def solve(
        self, qpos: np.ndarray, side: Side, position: np.ndarray, rotation: np.ndarray, point: np.ndarray
    ) -> np.ndarray:
        """Joint angles of ``side`` that put gripper-link point ``point`` at ``position`` with ``rotation``.

        ``qpos`` (the whole model's) seeds the search and fixes the other arm and the objects.
        """
        model, data, joints = self.model, self.data, ARM_QPOS[side]
        data.qpos[:] = qpos
        low, high = model.jnt_range[joints, 0], model.jnt_range[joints, 1]
        body = self.body[side]
        for _ in range(self.iterations):
            mujoco.mj_kinematics(model, data)
            mujoco.mj_comPos(model, data)
            current = data.xmat[body].reshape(3, 3)
            tip = data.xpos[body] + current @ point
            position_error = position - tip
            r = rotation @ current.T
            rotation_error = 0.5 * np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
            if np.linalg.norm(position_error) < 1e-5 and np.linalg.norm(rotation_error) < 1e-4:
                break
            mujoco.mj_jac(model, data, self._jacp, self._jacr, tip, body)
            jacobian = np.vstack([self._jacp[:, joints], self._jacr[:, joints]])
            error = np.concatenate([position_error, rotation_error])
            step = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + self.damping * np.eye(6), error)
            data.qpos[joints] = np.clip(data.qpos[joints] + step, low, high)
        return np.array(data.qpos[joints])

    def gravity_offset(self, qpos: np.ndarray) -> np.ndarray:
        """What to add to each robot position target so its servo holds ``qpos`` against gravity."""
        self.data.qpos[:] = qpos
        self.data.qvel[:] = 0
        mujoco.mj_forward(self.model, self.data)
        return np.asarray(self.data.qfrc_bias[:ROBOT_DOF] / self._gains)
