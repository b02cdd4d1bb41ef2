"""``leader_arm``: teleoperation. Each step commands the follower to the pose of the operator's leader arm.

The leader (an SO-100/SO-101 leader on its own Feetech bus, torque off, its own calibration) is
opened when the skill activates and read once per step; the action goes through the safety
envelope like any skill's, so a leader moved too fast is clamped, never passed through.
Its parameters (``vla.params``, or ``takeover.params`` as a deployment's takeover skill) are the
leader's bus settings (:class:`~openral_hal.feetech.leader.SO10xLeaderParams`): ``port`` and
``calibration``, or ``emulate: true`` with a ``trajectory`` to replay; both files are read when
the skill is built, so ``openral validate`` refuses what connecting would.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Self

from openral_core.actions import Action, ControlMode
from openral_core.robot import RobotManifest
from openral_core.skills import RSkillInfo
from openral_core.world import WorldState
from openral_hal.feetech.leader import SO10xLeaderArm
from openral_rskill.base import RSkillBase

SKILL_ID = "leader_arm"


class LeaderArmSkill(RSkillBase):
    """Follows the operator's leader arm.

    Args:
        robot: The follower; the leader has the same joints and servo ids.
        leader: The leader arm (not yet connected).
    """

    INFO = RSkillInfo(
        skill_id=SKILL_ID,
        name="Leader arm teleoperation",
        version="1.0.0",
        license="Apache-2.0",
        control_mode=ControlMode.JOINT_POSITION,
        chunk_size=1,
        description="Commands the follower to the pose of an SO-100/SO-101 leader arm.",
    )

    def __init__(self, robot: RobotManifest, leader: SO10xLeaderArm) -> None:
        super().__init__()
        self.robot = robot
        self.leader = leader
        self._names = robot.joint_names

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        """Build from ``vla.params`` (the leader's bus settings); nothing is opened until activation."""
        return cls(robot, SO10xLeaderArm(robot, params))

    @property
    def info(self) -> RSkillInfo:
        """Identity of the ``leader_arm`` skill."""
        return self.INFO

    def _on_activate(self) -> None:
        self.leader.connect()

    def _on_deactivate(self) -> None:
        self.leader.disconnect()

    def _on_shutdown(self) -> None:
        self.leader.disconnect()

    def _step_impl(self, world_state: WorldState) -> Action:
        pose = self.leader.read_state()
        return Action(
            control_mode=ControlMode.JOINT_POSITION,
            joint_names=self._names,
            targets=[pose.positions],
            stamp_ns=pose.stamp_ns,
            skill_id=SKILL_ID,
        )
