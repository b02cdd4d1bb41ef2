"""Robot manifests: the joints, limits and models that describe one robot type."""

from __future__ import annotations

from enum import StrEnum
from typing import Self

from pydantic import BaseModel, ConfigDict, Field, model_validator


class JointKind(StrEnum):
    """A revolute joint in radians, or a gripper.

    Gripper limits are in the robot model's own units (the SO-101 jaw: radians); an adapter
    for real hardware may expose a normalised opening, but limits here match the model.
    """

    REVOLUTE = "revolute"
    GRIPPER = "gripper"


class JointSpec(BaseModel):
    """One joint: its limits in the robot model's units (radians for revolute joints).

    Attributes:
        velocity_limit: Largest speed the actuator reaches, rad/s.
        servo_id: Bus id of the joint's servo on real hardware, when it has one.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1)
    kind: JointKind = JointKind.REVOLUTE
    lower: float
    upper: float
    velocity_limit: float = Field(gt=0)
    effort_limit: float | None = Field(default=None, gt=0)
    servo_id: int | None = Field(default=None, ge=0, le=253)

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if self.lower >= self.upper:
            raise ValueError(f"joint '{self.name}': lower ({self.lower}) must be below upper ({self.upper})")
        return self


class ModelRef(BaseModel):
    """Where the robot's MuJoCo model lives: a file inside an installed Python package."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    package: str
    path: str
    ee_site: str | None = None
    cameras: list[str] = Field(default_factory=list)


class RobotManifest(BaseModel):
    """``robots/<robot_id>/robot.yaml``: what every adapter and the safety client need to know."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    robot_id: str = Field(min_length=1)
    name: str = ""
    description: str = ""
    joints: list[JointSpec] = Field(min_length=1)
    base_frame: str = "base_link"
    mujoco: ModelRef | None = None
    source: str = ""

    @model_validator(mode="after")
    def _unique_joints(self) -> Self:
        names = [j.name for j in self.joints]
        if len(set(names)) != len(names):
            raise ValueError(f"robot '{self.robot_id}' repeats a joint name: {names}")
        return self

    @property
    def joint_names(self) -> list[str]:
        """Joint names in manifest order (the order of every action and joint state)."""
        return [j.name for j in self.joints]

    def joint(self, name: str) -> JointSpec:
        """One joint by name."""
        for spec in self.joints:
            if spec.name == name:
                return spec
        raise KeyError(name)
