"""Robot and world state: what the skill sees each tick."""

from __future__ import annotations

from typing import Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from openral_core.frames import SensorFrame
from openral_core.sim import PrivilegedState


class JointState(BaseModel):
    """Measured joint positions (rad, gripper 0..1 where noted by the robot manifest).

    ``velocities`` and ``efforts`` are optional; when present they align with ``names``.
    ``stamp_ns`` is the measurement time on the monotonic clock.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    names: list[str]
    positions: list[float]
    velocities: list[float] | None = None
    efforts: list[float] | None = None
    stamp_ns: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _aligned(self) -> Self:
        n = len(self.names)
        if len(set(self.names)) != n:
            raise ValueError(f"joint names must be unique, got {self.names}")
        for field in ("positions", "velocities", "efforts"):
            values = getattr(self, field)
            if values is not None and len(values) != n:
                raise ValueError(f"{field} has {len(values)} entries for {n} joint names")
        return self

    def position_of(self, name: str) -> float:
        """Position of one joint by name."""
        return self.positions[self.names.index(name)]


class Pose6D(BaseModel):
    """A pose: position in metres and orientation as roll/pitch/yaw in radians, in ``frame_id``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    frame_id: str = "base_link"


class ComponentDiagnostics(BaseModel):
    """Health of one world-state component (the joint state, or one sensor).

    Attributes:
        age_ms: Age of the freshest sample at snapshot time; ``None`` if none arrived yet.
        stale: The sample is missing or older than ``max_age_ms``.
        required: A stale required component withholds the tick's action.
        error: An error set on the component (overrides freshness until cleared).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    component: str
    age_ms: float | None = None
    max_age_ms: float | None = None
    stale: bool = False
    required: bool = True
    error: str | None = None

    @property
    def healthy(self) -> bool:
        """Fresh and free of errors."""
        return not self.stale and self.error is None


class WorldState(BaseModel):
    """A consistent snapshot of the robot and its sensors, taken once per tick.

    ``images`` carries ROS topic references (the ROS-native path); ``image_frames``
    carries the frames themselves for in-process deployments, keyed by sensor id.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    stamp_ns: int = Field(ge=0)
    joint_state: JointState | None = None
    ee_pose: Pose6D | None = None
    images: dict[str, str] = Field(default_factory=dict)
    image_frames: dict[str, SensorFrame] | None = None
    diagnostics: dict[str, ComponentDiagnostics] = Field(default_factory=dict)
    task: str | None = None
    privileged: PrivilegedState | None = None
    """Simulation only: what the simulator knows and a robot cannot measure (``None`` on hardware)."""

    @property
    def stale_components(self) -> list[str]:
        """Names of components that are stale or in error."""
        return [name for name, diag in self.diagnostics.items() if not diag.healthy]

    @property
    def stale_required(self) -> list[str]:
        """Names of required components that are stale or in error."""
        return [name for name, diag in self.diagnostics.items() if diag.required and not diag.healthy]
