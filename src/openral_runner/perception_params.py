"""Settings of the perception detectors and their publisher, validated without numpy work or GStreamer."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from openral_core.perception import ModelInputSize
from openral_remote.config import ZenohConfig

DEFAULT_EVENT_LISTEN = "tcp/127.0.0.1:7448"
"""Where the event publisher listens when the file names no endpoint: this machine only."""


class MotionParams(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold: float = Field(default=25.0, ge=0, lt=255, description="Grey-level step that counts as a change.")
    cell: int = Field(default=8, ge=1, description="Cell size in pixels.")
    min_cell_fraction: float = Field(default=0.25, gt=0, le=1, description="Changed pixels that make a cell change.")
    min_cells: int = Field(default=2, ge=1, description="Changed cells that make an event.")


class SceneChangeParams(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold: float = Field(default=0.5, gt=0, le=2, description="Chi-square distance (0–2) that is a change.")
    bins: int = Field(default=32, ge=2, le=256)


class ObjectsParams(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    model: str = Field(min_length=1, description="An ONNX detector with the RT-DETR signature.")
    labels: list[str] = Field(min_length=1, description="Class names, in the model's class order.")
    model_id: str | None = Field(default=None, description="Named in the events (default: the file's stem).")
    input_size: ModelInputSize = Field(default=(640, 640), description="The model's (height, width).")
    score_threshold: float = Field(default=0.5, ge=0, le=1)
    resize: Literal["stretch", "letterbox"] = Field(default="stretch", description="letterbox keeps the aspect.")


class PerceptionParams(BaseModel):
    """``params`` of the ``perception`` observer."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    sensors: list[str] | None = Field(default=None, description="Cameras to watch (default: every camera).")
    rate_hz: float = Field(default=5.0, gt=0, le=1000, description="Detections per second per camera and kind.")
    burst: int = Field(default=1, ge=1, le=100)
    motion: MotionParams | None = None
    scene_change: SceneChangeParams | None = None
    objects: ObjectsParams | None = None
    detector_manifest: str | None = Field(
        default=None, description="A kind: detector rSkill manifest (instead of objects), relative to the deployment."
    )
    zenoh: ZenohConfig | None = Field(
        default=None,
        description=f"Publish events on Zenoh with this session (listening on {DEFAULT_EVENT_LISTEN} unless it says).",
    )
    robot: str | None = Field(default=None, description="Robot segment of the Zenoh keys (default: the robot id).")
    ros2: bool = Field(default=False, description="Also publish on ROS 2 /openral/perception/<kind> (needs rclpy).")

    @field_validator("zenoh")
    @classmethod
    def _loopback_unless_told(cls, zenoh: ZenohConfig | None) -> ZenohConfig | None:
        """A peer session given no endpoint to listen on would listen on every interface (Zenoh's default)."""
        if zenoh is None or zenoh.mode != "peer" or zenoh.listen:
            return zenoh
        listen = "tcp/127.0.0.1:0" if zenoh.connect else DEFAULT_EVENT_LISTEN
        return zenoh.model_copy(update={"listen": [listen]})
