"""``libero_expert``: a scripted pick-and-place for LIBERO tasks, reading the simulator's privileged state.

For each placement of the goal in turn (``goal<i>_object_pos`` / ``_aabb`` / ``goal<i>_target_pos``,
which the ``libero`` environment exposes for every ``On``/``In`` predicate; or ``params.object``
and ``params.target`` by name): hover above the object, descend, close, lift, carry above the
target, lower until the object is just above it (or stops going down), open, rise. Then the next
placement; after the last, hold with the gripper open.

Positions are steered with proportional moves clipped to the action box; the gripper is held
pointing down, fingers across the world's y axis (a world-frame rotation-vector correction). Where to grasp comes
from the object's bounding box: its centre, at most ``finger_reach_m`` below its top (the centre of
a flat object); an object wider than the open gripper both ways (a bowl) is grasped at its rim, on
the +y side. Phases that wait on the gripper are counted in steps (nothing observable says when a
grasp is done), moves end within a tolerance or after a timeout, so the expert never stalls.
Deterministic: the same observations give the same actions.

Simulation only. It solves the custom pick-and-place scene, LIBERO-Object's tasks, most of
LIBERO-Spatial's and the placements of LIBERO-Goal and LIBERO-10; it cannot open drawers, turn
knobs or push.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from openral_core import Action, ControlMode, RobotManifest, RSkillInfo, WorldState
from openral_rskill.base import validate_params
from openral_sim.skills._base import ActionSpaceSkill, privileged

GRIPPER_OPEN = -1.0
GRIPPER_CLOSED = 1.0
DOWN_QUAT = np.array([1.0, 0.0, 0.0, 0.0])
"""The gripper pointing down, fingers across the world's y axis (x y z w)."""

_ROTATION_PER_UNIT = 0.5
"""Radians of LIBERO's OSC_POSE rotation target per action unit."""


class LiberoExpertParams(BaseModel):
    """``params`` of ``libero_expert`` (the defaults are the ones measured to succeed)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    object: str | None = Field(
        default=None, min_length=1, description="Object to pick (milk_1); by default the goal's."
    )
    target: str | None = Field(
        default=None, min_length=1, description="Body or region site to place it on or in (basket_1_contain_region)."
    )
    gain: float = Field(default=12.0, gt=0, le=1000, description="Action units per metre of position error.")
    hover_m: float = Field(default=0.12, gt=0, le=1, description="Above the grasp point before descending.")
    lift_m: float = Field(default=0.18, gt=0, le=1, description="Carry height above the higher of object and target.")
    place_m: float = Field(default=0.03, ge=0, le=1, description="The object is released this far above the target.")
    finger_reach_m: float = Field(default=0.04, gt=0, le=0.2, description="Grasp at most this far below the top.")
    rim_width_m: float = Field(default=0.10, gt=0, le=1, description="Wider than this both ways: grasp at the rim.")
    rim_inset_m: float = Field(default=0.028, ge=0, le=0.2, description="Rim grasp: this far in from the edge.")
    rim_depth_m: float = Field(default=0.015, ge=0, le=0.2, description="Rim grasp: this far below the top.")
    tolerance_m: float = Field(default=0.01, gt=0, le=0.2, description="A move ends within this distance.")
    close_steps: int = Field(default=15, ge=1, le=1000, description="Steps the fingers are given to close.")
    open_steps: int = Field(default=10, ge=1, le=1000, description="Steps the fingers are given to open.")
    timeout_steps: int = Field(default=80, ge=1, le=10_000, description="A move gives up after this many steps.")

    @model_validator(mode="after")
    def _both_or_neither(self) -> Self:
        if (self.object is None) != (self.target is None):
            raise ValueError("give both object and target, or neither (the goal's placements)")
        return self


class Phase(enum.Enum):
    APPROACH = enum.auto()
    DESCEND = enum.auto()
    CLOSE = enum.auto()
    LIFT = enum.auto()
    CARRY = enum.auto()
    LOWER = enum.auto()
    OPEN = enum.auto()
    RETREAT = enum.auto()
    DONE = enum.auto()


_HOLDING = (Phase.CLOSE, Phase.LIFT, Phase.CARRY, Phase.LOWER)


@dataclass(frozen=True)
class _Placement:
    """What one placement reads: the object's position and box, and where it goes."""

    position: np.ndarray
    aabb: np.ndarray
    target: np.ndarray


class LiberoExpert(ActionSpaceSkill):
    """Pick and place each of the goal's objects in turn; simulation only (privileged state)."""

    INFO = RSkillInfo(
        skill_id="libero_expert",
        name="LIBERO pick-and-place expert",
        version="1.0.0",
        control_mode=ControlMode.EE_DELTA,
        description="Scripted pick-and-place for LIBERO's On/In goals (privileged state, simulation only).",
    )

    def __init__(self, robot: RobotManifest, params: LiberoExpertParams) -> None:
        super().__init__(robot, ControlMode.EE_DELTA)
        self.params = params
        self._on_reset()

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(LiberoExpertParams, params, skill_id="libero_expert"))

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    @property
    def phase(self) -> Phase:
        return self._phase

    def _on_reset(self) -> None:
        self._phase = Phase.APPROACH
        self._placement = 0
        self._steps = 0
        self._held = np.zeros(3)
        self._carry_z = 0.0
        self._heights: list[float] = []

    def _on_activate(self) -> None:
        self._on_reset()

    def _step_impl(self, world_state: WorldState) -> Action:
        eef = privileged(world_state, "eef_pos")
        quat = privileged(world_state, "eef_quat")
        goal, gripper = eef, GRIPPER_OPEN
        for _ in range(len(Phase)):  # at most one pass through every phase per step
            placement = self._read(world_state)
            if placement is None:
                self._phase = Phase.DONE
                break
            goal, gripper, finished = self._plan(placement, eef)
            if not finished:
                break
            self._advance(placement, eef)
        self._steps += 1
        action = np.zeros(7)
        action[:3] = np.clip((goal - eef) * self.params.gain, -1.0, 1.0)
        action[3:6] = np.clip(_rotation_error(DOWN_QUAT, quat) / _ROTATION_PER_UNIT * 2.0, -1.0, 1.0)
        action[6] = gripper
        return self.emit(action, world_state)

    def _read(self, world_state: WorldState) -> _Placement | None:
        """The current placement's values, or ``None`` once every placement is done."""
        p = self.params
        if p.object is not None and p.target is not None:
            if self._placement > 0:
                return None
            names = (f"{p.object}_pos", f"{p.object}_aabb", f"{p.target}_pos")
        else:
            goal = f"goal{self._placement}"
            names = (f"{goal}_object_pos", f"{goal}_object_aabb", f"{goal}_target_pos")
            if world_state.privileged is not None and names[0] not in world_state.privileged.values:
                return None
        position, aabb, target = (privileged(world_state, name) for name in names)
        return _Placement(position, aabb, target)

    def _plan(self, placement: _Placement, eef: np.ndarray) -> tuple[np.ndarray, float, bool]:
        """This phase's goal for the gripper, its finger command, and whether the phase is over."""
        p = self.params
        timed_out = self._steps >= p.timeout_steps
        phase = self._phase
        gripper = GRIPPER_CLOSED if phase in _HOLDING else GRIPPER_OPEN
        if phase in (Phase.APPROACH, Phase.DESCEND, Phase.CLOSE):
            grasp = self._grasp_point(placement.aabb)
            if phase is Phase.APPROACH:
                goal = grasp + np.array([0.0, 0.0, p.hover_m])
                return goal, gripper, timed_out or _near(goal, eef, p.tolerance_m)
            finished = (
                self._steps >= p.close_steps
                if phase is Phase.CLOSE
                else timed_out or abs(grasp[2] - eef[2]) < p.tolerance_m
            )
            return grasp, gripper, finished
        above = placement.target[:2] + self._held[:2]
        if phase is Phase.LIFT:
            goal = np.array([eef[0], eef[1], self._carry_z])
            return goal, gripper, timed_out or abs(goal[2] - eef[2]) < 2 * p.tolerance_m
        if phase is Phase.CARRY:
            goal = np.array([*above, self._carry_z])
            return goal, gripper, timed_out or _near(goal[:2], eef[:2], p.tolerance_m)
        if phase is Phase.LOWER:
            goal = np.array([*above, placement.target[2] + self._held[2] + p.place_m])
            self._heights.append(float(eef[2]))
            stalled = len(self._heights) > 10 and self._heights[-11] - eef[2] < 0.003
            return goal, gripper, timed_out or stalled or abs(goal[2] - eef[2]) < p.tolerance_m
        if phase is Phase.OPEN:
            return eef, gripper, self._steps >= p.open_steps
        goal = np.array([eef[0], eef[1], self._carry_z])
        return goal, gripper, timed_out or abs(goal[2] - eef[2]) < 2 * p.tolerance_m

    def _advance(self, placement: _Placement, eef: np.ndarray) -> None:
        """Leave the current phase (on to the next placement after rising from this one)."""
        if self._phase is Phase.CLOSE:
            # How the object hangs from the gripper: it is put down by where the gripper goes.
            self._held = eef - placement.position
            self._carry_z = float(max(placement.aabb[5], placement.target[2]) + self.params.lift_m)
        if self._phase is Phase.CARRY:
            self._heights = []
        if self._phase is Phase.RETREAT:
            self._placement += 1
            self._phase = Phase.APPROACH
        else:
            self._phase = Phase(self._phase.value + 1)
        self._steps = 0

    def _grasp_point(self, aabb: np.ndarray) -> np.ndarray:
        """Where the fingertips close on an object with this bounding box."""
        p = self.params
        low, high = aabb[:3], aabb[3:]
        centre = (low + high) / 2
        size = high - low
        if size[0] > p.rim_width_m and size[1] > p.rim_width_m:
            return np.array([centre[0], high[1] - p.rim_inset_m, high[2] - p.rim_depth_m])
        return np.array([centre[0], centre[1], max(centre[2], high[2] - p.finger_reach_m)])


def _near(a: np.ndarray, b: np.ndarray, tolerance: float) -> bool:
    return bool(np.linalg.norm(a - b) < tolerance)


def _rotation_error(reference: np.ndarray, current: np.ndarray) -> np.ndarray:
    """The world-frame rotation vector taking ``current`` to ``reference`` (quaternions x y z w)."""
    rx, ry, rz, rw = reference
    cx, cy, cz, cw = -current[0], -current[1], -current[2], current[3]  # the conjugate of current
    error = np.array(
        [
            rw * cx + rx * cw + ry * cz - rz * cy,
            rw * cy - rx * cz + ry * cw + rz * cx,
            rw * cz + rx * cy - ry * cx + rz * cw,
            rw * cw - rx * cx - ry * cy - rz * cz,
        ]
    )
    if error[3] < 0:
        error = -error  # the shorter way round
    sine = float(np.linalg.norm(error[:3]))
    if sine < 1e-12:
        return np.zeros(3)
    return np.asarray(error[:3] / sine * 2.0 * np.arctan2(sine, error[3]))
