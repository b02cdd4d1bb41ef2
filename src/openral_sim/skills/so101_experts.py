"""Scripted SO-101 experts on privileged state: ``so101_pick_expert`` and ``so101_pickplace_expert``.

Both command ``[dx, dy, dz, grasp]`` moves of the grasp point (``grasp_pos``) towards a phase's
target, proportional to the remaining error in action units and clipped (slower near the
block). The pick is a phase machine: hover above the block, descend to grasp height, close the
jaw for a fixed number of steps (nothing observable changes while it closes, so the phase is
state, not a function of one observation), lift. The pick-and-place expert is the controller
``lerobot-env-so101`` ships, driven by the same privileged values.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import Action, ControlMode, RobotManifest, RSkillInfo, WorldState
from openral_rskill.base import validate_params
from openral_sim.skills._base import ActionSpaceSkill, privileged

GRIPPER_OPEN = 1.0
GRIPPER_CLOSED = 0.0


class PickParams(BaseModel):
    """``params`` of ``so101_pick_expert`` (the defaults are the ones measured to succeed)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    action_scale: float = Field(default=0.025, gt=0, le=1, description="The env's metres per unit of position action.")
    hover_height_m: float = Field(default=0.07, gt=0, le=1, description="Above the block's centre before descending.")
    grasp_height_m: float = Field(default=0.015, ge=0, le=1, description="Grasp point above the block's centre.")
    lift_height_m: float = Field(default=0.13, gt=0, le=1, description="How far to lift the block.")
    close_steps: int = Field(default=10, ge=1, le=10_000, description="Steps the jaw is given to close.")
    tolerance_m: float = Field(default=0.004, gt=0, le=1, description="A moving phase ends within this distance.")
    careful_speed: float = Field(default=0.4, gt=0, le=1, description="Largest action near the block.")
    phase_timeout_steps: int = Field(
        default=60, ge=1, le=100_000, description="A moving phase gives up after this many steps."
    )


class _Phase(enum.Enum):
    HOVER = enum.auto()
    DESCEND = enum.auto()
    CLOSE = enum.auto()
    LIFT = enum.auto()


class SO101PickExpert(ActionSpaceSkill):
    """Hover, descend, close, lift: the block and grasp point read from the simulator."""

    INFO = RSkillInfo(
        skill_id="so101_pick_expert",
        name="SO-101 pick expert",
        version="1.0.0",
        control_mode=ControlMode.EE_DELTA,
        description="Scripted pick for SO101PickCube-v0 on privileged state (simulation only).",
    )

    def __init__(self, robot: RobotManifest, params: PickParams) -> None:
        super().__init__(robot, ControlMode.EE_DELTA)
        self.params = params
        self._phase = _Phase.HOVER
        self._steps_in_phase = 0
        self._block_z0: float | None = None
        self._grasp_xy = np.zeros(2)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(PickParams, params, skill_id="so101_pick_expert"))

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def _on_reset(self) -> None:
        self._phase = _Phase.HOVER
        self._steps_in_phase = 0
        self._block_z0 = None

    def _on_activate(self) -> None:
        self._on_reset()

    def _step_impl(self, world_state: WorldState) -> Action:
        p = self.params
        grasp = privileged(world_state, "grasp_pos")
        block = privileged(world_state, "block_pos")
        if self._block_z0 is None:
            self._block_z0 = float(block[2])
        while True:
            error = self._target(block) - grasp
            limit = 1.0 if self._phase is _Phase.HOVER else p.careful_speed
            delta = np.clip(error / p.action_scale, -limit, limit)
            if self._phase is _Phase.CLOSE:
                # Keep steering at the grasp target while the jaw closes: a zero move would let the
                # env latch wherever the arm sagged to.
                finished = self._steps_in_phase >= p.close_steps
            else:
                finished = self._phase is not _Phase.LIFT and bool(
                    np.linalg.norm(error) < p.tolerance_m or self._steps_in_phase >= p.phase_timeout_steps
                )
            if not finished:
                break
            self._phase = _Phase(self._phase.value + 1)
            self._steps_in_phase = 0
        self._steps_in_phase += 1
        jaw = GRIPPER_OPEN if self._phase in (_Phase.HOVER, _Phase.DESCEND) else GRIPPER_CLOSED
        return self.emit([*delta, jaw], world_state)

    def _target(self, block: np.ndarray) -> np.ndarray:
        """Where the grasp point should be in the current phase (above the block until it is held)."""
        p = self.params
        if self._phase in (_Phase.HOVER, _Phase.DESCEND):
            self._grasp_xy = block[:2].copy()
        z0 = self._block_z0 if self._block_z0 is not None else float(block[2])
        height = {
            _Phase.HOVER: p.hover_height_m,
            _Phase.DESCEND: p.grasp_height_m,
            _Phase.CLOSE: p.grasp_height_m,
            _Phase.LIFT: p.grasp_height_m + p.lift_height_m,
        }[self._phase]
        return np.array([self._grasp_xy[0], self._grasp_xy[1], z0 + height])


class PickPlaceParams(BaseModel):
    """``params`` of ``so101_pickplace_expert``."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    action_scale: float = Field(default=0.025, gt=0, le=1, description="The env's metres per unit of position action.")


class SO101PickPlaceExpert(ActionSpaceSkill):
    """``lerobot-env-so101``'s ``PickPlaceController`` fed from privileged state."""

    INFO = RSkillInfo(
        skill_id="so101_pickplace_expert",
        name="SO-101 pick-and-place expert",
        version="1.0.0",
        control_mode=ControlMode.EE_DELTA,
        description="The PickPlaceController of lerobot-env-so101 for SO101PickPlace-v0 (simulation only).",
    )

    def __init__(self, robot: RobotManifest, params: PickPlaceParams) -> None:
        super().__init__(robot, ControlMode.EE_DELTA)
        from lerobot_env_so101.scripted import PickPlaceController  # noqa: PLC0415

        self._controller = PickPlaceController(action_scale=params.action_scale)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(PickPlaceParams, params, skill_id="so101_pickplace_expert"))

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def _on_reset(self) -> None:
        self._controller.reset()

    def _on_activate(self) -> None:
        self._controller.reset()

    def _step_impl(self, world_state: WorldState) -> Action:
        action = self._controller.act(
            privileged(world_state, "grasp_pos"),
            privileged(world_state, "block_pos"),
            privileged(world_state, "goal_pos"),
        )
        return self.emit(action, world_state)
