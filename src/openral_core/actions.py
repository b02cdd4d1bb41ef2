"""Actions a skill emits and the safety envelope they are checked against."""

from __future__ import annotations

import math
from enum import StrEnum
from typing import Self

from pydantic import BaseModel, ConfigDict, Field, model_validator


class ControlMode(StrEnum):
    """How an action's values are interpreted by the HAL."""

    JOINT_POSITION = "joint_position"
    JOINT_VELOCITY = "joint_velocity"
    JOINT_TORQUE = "joint_torque"
    EE_POSE = "ee_pose"
    EE_DELTA = "ee_delta"


class Action(BaseModel):
    """A command for the robot: ``targets[k][j]`` is the value for joint ``j`` at step ``k``.

    ``horizon`` (the number of rows) is 1 for a single command and larger for an action
    chunk; the HAL applies row 0. Non-finite values are representable on purpose so that
    the safety client, not the constructor, rejects them and the rejection is traced.
    In JSON they are written as ``NaN`` / ``Infinity`` so they survive a round trip.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", ser_json_inf_nan="constants")

    control_mode: ControlMode = ControlMode.JOINT_POSITION
    joint_names: list[str]
    targets: list[list[float]] = Field(min_length=1)
    confidence: list[float] | None = None
    stamp_ns: int = Field(default=0, ge=0)
    skill_id: str | None = None

    @model_validator(mode="after")
    def _rectangular(self) -> Self:
        n = len(self.joint_names)
        for k, row in enumerate(self.targets):
            if len(row) != n:
                raise ValueError(f"targets[{k}] has {len(row)} values for {n} joint names")
        return self

    @classmethod
    def trusted(
        cls,
        *,
        control_mode: ControlMode,
        joint_names: list[str],
        targets: list[list[float]],
        stamp_ns: int,
        skill_id: str | None,
    ) -> Action:
        """An ``Action`` of values a component computed itself, without validating them again.

        For a path taken every tick (the chunk executor's row); the caller guarantees the types
        and the shape. Input from outside goes through ``Action(...)``.
        """
        action = cls.__new__(cls)
        values = {
            "control_mode": control_mode,
            "joint_names": joint_names,
            "targets": targets,
            "confidence": None,
            "stamp_ns": stamp_ns,
            "skill_id": skill_id,
        }
        object.__setattr__(action, "__dict__", values)
        object.__setattr__(action, "__pydantic_fields_set__", set(values))
        object.__setattr__(action, "__pydantic_extra__", None)
        object.__setattr__(action, "__pydantic_private__", None)
        return action

    @property
    def horizon(self) -> int:
        """Number of steps in the action (1 unless it is a chunk)."""
        return len(self.targets)

    @property
    def first(self) -> list[float]:
        """The step the HAL applies now."""
        return self.targets[0]


def action_problem(output: object) -> str | None:
    """Why ``output`` (what a skill's ``step`` returned) is not an action the runner can check and send.

    ``None`` when it is one. Cheap enough for every tick: type checks only, no validation pass.
    Catches what pydantic would have refused had the action not been built with
    ``model_construct`` or mutated afterwards: a non-``Action``, ``None``, numpy rows, ``None`` or
    text values, empty or ragged targets. Non-finite numbers are left to the safety client.
    """
    if not isinstance(output, Action):
        return f"step returned {type(output).__name__}, not an Action"
    names = output.joint_names
    targets = output.targets
    if type(names) is not list or not names or not all(type(name) is str for name in names):
        return "joint_names must be a non-empty list of joint names"
    if type(targets) is not list or not targets:
        return "targets must hold at least one row"
    n = len(names)
    for k, row in enumerate(targets):
        if type(row) is not list:
            return f"targets[{k}] is {type(row).__name__}, not a list of numbers"
        if len(row) != n:
            return f"targets[{k}] has {len(row)} values for {n} joint names"
        for value in row:
            kind = type(value)
            if kind is not float and kind is not int:
                return f"targets[{k}] holds {kind.__name__} {value!r:.40}, not a number"
    if not isinstance(output.control_mode, ControlMode):
        return f"control_mode {output.control_mode!r:.40} is not a control mode"
    return None


class SafetyMode(StrEnum):
    """What the safety client does with an action outside the envelope."""

    CLAMP = "clamp"
    REJECT = "reject"


class SafetyEnvelope(BaseModel):
    """Limits an action must respect beyond the robot's own joint limits.

    Attributes:
        max_joint_speed_factor: Fraction of each joint's velocity limit allowed per tick.
        workspace_min / workspace_max: Optional Cartesian box (metres, base frame) for the end effector.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    max_ee_speed_m_s: float = Field(default=0.5, gt=0)
    max_force_n: float = Field(default=50.0, gt=0)
    max_joint_speed_factor: float = Field(default=1.0, gt=0, le=1.0)
    workspace_min: tuple[float, float, float] | None = None
    workspace_max: tuple[float, float, float] | None = None

    @model_validator(mode="after")
    def _box(self) -> Self:
        check_workspace_box(self.workspace_min, self.workspace_max)
        return self


def check_workspace_box(lower: tuple[float, float, float] | None, upper: tuple[float, float, float] | None) -> None:
    """Both corners or neither, finite, and ``lower < upper`` on every axis.

    Raises:
        ValueError: The box is malformed (pydantic reports it against the model).
    """
    if (lower is None) != (upper is None):
        raise ValueError("workspace_min and workspace_max must be given together")
    if lower is None or upper is None:
        return
    for axis, lo, hi in zip("xyz", lower, upper, strict=True):
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"workspace bounds on {axis} must be finite, got [{lo}, {hi}]")
        if lo >= hi:
            raise ValueError(f"workspace_min.{axis} ({lo}) must be below workspace_max.{axis} ({hi})")
