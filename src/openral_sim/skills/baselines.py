"""``zero`` and ``random``: the baselines every evaluation is compared with.

``zero`` sends the middle of each bound that straddles zero (zero motion in a delta space);
``random`` draws uniformly inside the bounds from a generator seeded with the episode's seed, so
its episodes reproduce.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import Action, ControlMode, RobotManifest, RSkillInfo, WorldState
from openral_rskill.base import validate_params
from openral_sim.skills._base import ActionSpaceSkill

MAX_SEED = 2**63 - 1
"""Largest seed accepted: one that fits the signed 64-bit integers results and datasets store seeds in."""


class ZeroParams(BaseModel):
    """``params`` of the ``zero`` skill: none; any key is an error."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class ZeroSkill(ActionSpaceSkill):
    """Sends zero in every dimension whose bounds contain it, else the nearest bound."""

    INFO = RSkillInfo(skill_id="zero", name="Zero", version="1.0.0", description="Zero action (clamped to bounds).")

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        validate_params(ZeroParams, params, skill_id="zero")
        return cls(robot, ControlMode.EE_DELTA)

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def _step_impl(self, world_state: WorldState) -> Action:
        return self.emit(np.clip(0.0, self.low, self.high), world_state)


class RandomParams(BaseModel):
    """``params`` of the ``random`` skill."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    seed: int = Field(default=0, ge=0, le=MAX_SEED)
    """Used when the runner gives no episode seed (on hardware this skill has no business running)."""


class RandomSkill(ActionSpaceSkill):
    """Uniform random actions inside the bounds, reproducible per episode seed."""

    INFO = RSkillInfo(skill_id="random", name="Random", version="1.0.0", description="Uniform random actions.")

    def __init__(self, robot: RobotManifest, seed: int) -> None:
        super().__init__(robot, ControlMode.EE_DELTA)
        self._seed = seed
        self._rng = np.random.default_rng(seed)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(RandomParams, params, skill_id="random").seed)

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def _on_reset(self) -> None:
        self._rng = np.random.default_rng(self._seed if self.episode_seed is None else self.episode_seed)

    def _step_impl(self, world_state: WorldState) -> Action:
        return self.emit(self._rng.uniform(self.low, self.high), world_state)
