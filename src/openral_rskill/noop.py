"""``noop``: hold the pose measured at the start of the episode.

The no-op skill for benchmarks and bring-up: it costs almost nothing per step, so a tick's time
is the runner's own overhead, and the robot stays where it was.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Self

from pydantic import BaseModel, ConfigDict

from openral_core.actions import Action, ControlMode
from openral_core.robot import RobotManifest
from openral_core.skills import RSkillInfo
from openral_core.world import WorldState
from openral_rskill.base import RSkillBase, validate_params
from openral_rskill.pose import clamp_to_limits, measured_pose

SKILL_ID = "noop"


class HoldParams(BaseModel):
    """``vla.params`` of the ``noop`` skill: none; any key is an error."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class HoldSkill(RSkillBase):
    """Commands, every step, the pose measured on the first step after ``activate``/``reset``.

    The latched pose is clamped into the joint limits, so a start pose a hair outside a limit is
    held at the limit rather than rejected by the safety client on every tick.

    Args:
        robot: The robot it commands; every action names all of its joints, in manifest order.
    """

    INFO = RSkillInfo(
        skill_id=SKILL_ID,
        name="Hold",
        version="1.0.0",
        license="Apache-2.0",
        control_mode=ControlMode.JOINT_POSITION,
        chunk_size=1,
        description="Holds the pose measured at the start of the episode.",
    )

    def __init__(self, robot: RobotManifest) -> None:
        super().__init__()
        self.robot = robot
        self._names = robot.joint_names
        self._pose: list[float] | None = None

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        """Build from ``vla.params`` (which must be empty); ``rate_hz`` is not needed."""
        validate_params(HoldParams, params, skill_id=SKILL_ID)
        return cls(robot)

    @property
    def info(self) -> RSkillInfo:
        """Identity of the ``noop`` skill."""
        return self.INFO

    @property
    def held_pose(self) -> list[float] | None:
        """The latched pose (manifest order), ``None`` until the episode's first step."""
        return None if self._pose is None else list(self._pose)

    def _on_activate(self) -> None:
        self._pose = None

    def _on_reset(self) -> None:
        self._pose = None

    def _step_impl(self, world_state: WorldState) -> Action:
        pose = self._pose
        if pose is None:
            pose = self._pose = clamp_to_limits(measured_pose(world_state, self._names), self.robot)
        return Action(
            control_mode=ControlMode.JOINT_POSITION,
            joint_names=self._names,
            targets=[pose],
            stamp_ns=world_state.stamp_ns,
            skill_id=SKILL_ID,
        )
