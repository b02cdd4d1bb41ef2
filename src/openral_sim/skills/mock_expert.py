"""``mock_reach_expert``: the ``mock`` environment's scripted expert (steps straight at the target)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import Action, ControlMode, RobotManifest, RSkillInfo, WorldState
from openral_rskill.base import validate_params
from openral_sim.skills._base import ActionSpaceSkill, privileged


class MockExpertParams(BaseModel):
    """``params`` of ``mock_reach_expert``."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    gain: float = Field(default=20.0, gt=0, le=1e6, description="Action per unit of distance to the target.")


class MockReachExpert(ActionSpaceSkill):
    """Moves the point towards the privileged target, proportionally, clipped to the action box."""

    INFO = RSkillInfo(skill_id="mock_reach_expert", name="Mock reach expert", version="1.0.0")

    def __init__(self, robot: RobotManifest, gain: float) -> None:
        super().__init__(robot, ControlMode.EE_DELTA)
        self.gain = gain

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(MockExpertParams, params, skill_id="mock_reach_expert").gain)

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def _step_impl(self, world_state: WorldState) -> Action:
        error = privileged(world_state, "target") - privileged(world_state, "position")
        return self.emit(np.clip(error * self.gain, self.low, self.high), world_state)
