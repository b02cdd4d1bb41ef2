"""Scripted ALOHA experts on privileged state: ``aloha_transfer_cube_expert`` and ``aloha_insertion_expert``.

Neither gym-aloha nor LeRobot ships one. Each expert reads the object poses once, at the first
step of an episode, and lays out a timed plan of gripper keyframes for both arms (a point near
the fingertips, its orientation, the gripper opening); every step then follows the plan through
inverse kinematics (:mod:`openral_sim.skills.aloha_kinematics`). The plan depends on the seed's
object poses alone, so an episode is deterministic.

Transfer cube: the right arm grasps the cube tilted 70° down, lifts it and holds it out at the
middle of the table pointing at the left arm; the left gripper, rolled 90° so its fingers close
across the right ones, takes it; the right gripper opens and both withdraw.
Insertion: each arm grasps its part from above, 3 cm off centre towards the middle; both lift,
align the peg with the socket's bore above the table, and the right arm slides the peg in until
it touches the pin.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import Action, ControlMode, RobotManifest, RSkillInfo, WorldState
from openral_rskill.base import validate_params
from openral_sim.skills._base import ActionSpaceSkill, privileged
from openral_sim.skills.aloha_kinematics import (
    ARM_QPOS,
    ROBOT_DOF,
    SIDES,
    Keyframe,
    Side,
    ViperXKinematics,
    frame,
    sample,
)

try:
    import mujoco
    from gym_aloha.constants import ASSETS_DIR
except ImportError as exc:
    from openral_core import ROSDependencyMissing

    raise ROSDependencyMissing(exc.name or "gym_aloha", extra="aloha", needed_for="the ALOHA experts") from exc

FINGERTIP = 0.154
"""How far the fingertips lie along the gripper link's x axis, in metres (from the finger mesh)."""
OPEN, CLOSED = 1.0, 0.0
CUBE_REST_Z = 0.02
PEG_REST_Z = 0.01
SOCKET_GRASP_Z = 0.022

Plan = dict[Side, tuple[list[Keyframe], np.ndarray]]
"""Per arm: its keyframes and the gripper-link point they place."""
_ACTION_OFFSETS: tuple[tuple[int, Side], ...] = ((0, "left"), (7, "right"))
"""Where each arm's seven values start in the action (six joints, then the gripper)."""


class AlohaExpertParams(BaseModel):
    """``params`` of the ALOHA experts."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    gravity_compensation: bool = Field(
        default=True, description="Offset each joint target by the gravity torque over the servo's gain."
    )


def shifted(point: np.ndarray, *, dx: float = 0.0, dy: float = 0.0, dz: float = 0.0) -> np.ndarray:
    """``point`` moved by ``(dx, dy, dz)`` metres."""
    return np.asarray(point + np.array([dx, dy, dz]))


def _start(kin: ViperXKinematics, qpos: np.ndarray, point: dict[Side, np.ndarray]) -> dict[Side, Keyframe]:
    """Where each arm's controlled point is now: the first keyframe, so the plan starts without a jump."""
    keys = {}
    for side in SIDES:
        position, rotation = kin.gripper_pose(qpos, side)
        keys[side] = Keyframe(0, position + rotation @ point[side], rotation, OPEN)
    return keys


def transfer_cube_plan(kin: ViperXKinematics, qpos: np.ndarray) -> Plan:
    """Right arm picks the cube and holds it out; the left arm takes it at the middle of the table."""
    cube = qpos[ROBOT_DOF : ROBOT_DOF + 3].copy()
    cube[2] = CUBE_REST_Z
    tilt = np.deg2rad(70)
    pick = frame([-np.cos(tilt), 0, -np.sin(tilt)], [0, -1, 0])
    hold = frame([-1, 0, 0], [0, -1, 0])
    take = frame([1, 0, 0], [0, 0, 1])
    handover = np.array([0.0, 0.5, 0.25])
    point: dict[Side, np.ndarray] = {"right": np.array([FINGERTIP, 0, 0]), "left": np.array([FINGERTIP + 0.006, 0, 0])}
    start = _start(kin, qpos, point)
    up = np.array([0, 0, 0.08])
    right = [
        start["right"],
        Keyframe(60, cube + up, pick, OPEN),
        Keyframe(90, cube, pick, OPEN),
        Keyframe(105, cube, pick, CLOSED),
        Keyframe(115, shifted(cube, dz=0.05), pick, CLOSED),
        Keyframe(165, handover, hold, CLOSED),
        Keyframe(215, handover, hold, CLOSED),
        Keyframe(230, handover, hold, OPEN),
        Keyframe(260, shifted(handover, dx=0.08), hold, OPEN),
    ]
    left = [
        start["left"],
        Keyframe(120, shifted(handover, dx=-0.10), take, OPEN),
        Keyframe(165, shifted(handover, dx=-0.10), take, OPEN),
        Keyframe(195, handover, take, OPEN),
        Keyframe(215, handover, take, CLOSED),
        Keyframe(260, shifted(handover, dx=-0.08), take, CLOSED),
    ]
    return {"right": (right, point["right"]), "left": (left, point["left"])}


def insertion_plan(kin: ViperXKinematics, qpos: np.ndarray) -> Plan:
    """Each arm grasps its part from above; the right arm slides the peg into the socket."""
    peg = qpos[ROBOT_DOF : ROBOT_DOF + 3].copy()
    peg[2] = PEG_REST_Z
    socket = qpos[ROBOT_DOF + 7 : ROBOT_DOF + 10].copy()
    socket[2] = SOCKET_GRASP_Z
    down_right = frame([0, 0, -1], [0, -1, 0])
    down_left = frame([0, 0, -1], [0, 1, 0])
    tip = np.array([FINGERTIP - 0.004, 0, 0])
    point: dict[Side, np.ndarray] = {"right": tip, "left": tip}
    start = _start(kin, qpos, point)
    grasp_right, grasp_left = shifted(peg, dx=0.03), shifted(socket, dx=-0.03)
    # The socket's centre when the peg goes in; the peg's far end must reach past the pin (4 cm in).
    meet = np.array([-0.05, 0.5, 0.20])
    before, inserted = shifted(meet, dx=0.19), shifted(meet, dx=0.122)
    up, lift = np.array([0, 0, 0.08]), np.array([0, 0, 0.04])
    right = [
        start["right"],
        Keyframe(70, grasp_right + up, down_right, OPEN),
        Keyframe(100, grasp_right, down_right, OPEN),
        Keyframe(115, grasp_right, down_right, CLOSED),
        Keyframe(125, grasp_right + lift, down_right, CLOSED),
        Keyframe(175, before, down_right, CLOSED),
        Keyframe(200, before, down_right, CLOSED),
        Keyframe(260, inserted, down_right, CLOSED),
    ]
    left = [
        start["left"],
        Keyframe(70, grasp_left + up, down_left, OPEN),
        Keyframe(100, grasp_left, down_left, OPEN),
        Keyframe(115, grasp_left, down_left, CLOSED),
        Keyframe(125, grasp_left + lift, down_left, CLOSED),
        Keyframe(175, shifted(meet, dx=-0.03), down_left, CLOSED),
    ]
    return {"right": (right, point["right"]), "left": (left, point["left"])}


class _AlohaExpert(ActionSpaceSkill):
    """Plans at an episode's first step from privileged ``qpos``, then follows the plan in joint space."""

    INFO: RSkillInfo
    MODEL_FILE: str
    PLAN: Callable[[ViperXKinematics, np.ndarray], Plan]

    def __init__(self, robot: RobotManifest, params: AlohaExpertParams) -> None:
        super().__init__(robot, ControlMode.JOINT_POSITION)
        self.params = params
        self._kin = ViperXKinematics(mujoco.MjModel.from_xml_path(str(ASSETS_DIR / self.MODEL_FILE)))
        self._plan: Plan | None = None
        self._steps = 0
        self._targets = np.zeros(self._kin.model.nq)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(AlohaExpertParams, params, skill_id=cls.INFO.skill_id))

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def _on_reset(self) -> None:
        self._plan = None
        self._steps = 0

    def _on_activate(self) -> None:
        self._on_reset()

    def _step_impl(self, world_state: WorldState) -> Action:
        qpos = privileged(world_state, "qpos")
        if self._plan is None:
            self._plan = type(self).PLAN(self._kin, qpos)
            self._targets = qpos.copy()
        self._steps += 1
        action = np.zeros(len(self.names))
        for offset, side in _ACTION_OFFSETS:
            keys, point = self._plan[side]
            key = sample(keys, self._steps)
            joints = ARM_QPOS[side]
            self._targets[joints] = self._kin.solve(self._targets, side, key.position, key.rotation, point)
            action[offset : offset + 6] = self._targets[joints]
            action[offset + 6] = key.opening
        if self.params.gravity_compensation:
            offset_torque = self._kin.gravity_offset(self._targets)
            action[0:6] += offset_torque[ARM_QPOS["left"]]
            action[7:13] += offset_torque[ARM_QPOS["right"]]
        return self.emit(action, world_state)


class TransferCubeExpert(_AlohaExpert):
    """The right arm picks the cube and hands it to the left (``AlohaTransferCube-v0``; simulation only)."""

    INFO = RSkillInfo(
        skill_id="aloha_transfer_cube_expert",
        name="ALOHA transfer-cube expert",
        version="1.0.0",
        control_mode=ControlMode.JOINT_POSITION,
        description="Scripted bimanual cube handover in joint space on privileged state (simulation only).",
    )
    MODEL_FILE = "bimanual_viperx_transfer_cube.xml"
    PLAN = staticmethod(transfer_cube_plan)


class InsertionExpert(_AlohaExpert):
    """Both arms pick their part and the peg goes into the socket (``AlohaInsertion-v0``; simulation only)."""

    INFO = RSkillInfo(
        skill_id="aloha_insertion_expert",
        name="ALOHA insertion expert",
        version="1.0.0",
        control_mode=ControlMode.JOINT_POSITION,
        description="Scripted bimanual peg insertion in joint space on privileged state (simulation only).",
    )
    MODEL_FILE = "bimanual_viperx_insertion.xml"
    PLAN = staticmethod(insertion_plan)
