"""What perception reports beside the policy: motion, scene changes, detected objects, as events."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

MAX_MODEL_INPUT_SIDE = 8192
"""Largest side of a detector's input accepted from a configuration: far above any real model."""

ModelInputSide = Annotated[int, Field(ge=1, le=MAX_MODEL_INPUT_SIDE)]
ModelInputSize = tuple[ModelInputSide, ModelInputSide]
"""A detector model's ``(height, width)`` in pixels, each side 1 to :data:`MAX_MODEL_INPUT_SIDE`."""


class PixelBox(BaseModel):
    """An axis-aligned box in pixels: ``x0 <= x1``, ``y0 <= y1``, corners inclusive of the area covered."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    x0: float
    y0: float
    x1: float
    y1: float

    @model_validator(mode="after")
    def _ordered(self) -> PixelBox:
        if self.x1 < self.x0 or self.y1 < self.y0:
            raise ValueError(f"corners out of order: ({self.x0}, {self.y0}) to ({self.x1}, {self.y1})")
        return self

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    def iou(self, other: PixelBox) -> float:
        """Intersection over union with ``other`` (0 when either is empty)."""
        width = min(self.x1, other.x1) - max(self.x0, other.x0)
        height = min(self.y1, other.y1) - max(self.y0, other.y0)
        if width <= 0 or height <= 0:
            return 0.0
        inter = width * height
        union = self.area + other.area - inter
        return inter / union if union > 0 else 0.0


class MotionMetadata(BaseModel):
    """Pixels changed since the previous frame: how much, and where."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["motion"] = "motion"
    changed_fraction: float = Field(ge=0, le=1, description="Fraction of the frame's cells that changed.")
    box: PixelBox = Field(description="The changed region's extent.")


class SceneChangeMetadata(BaseModel):
    """The grey histogram moved away from the previous frame's."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["scene_change"] = "scene_change"
    distance: float = Field(ge=0, description="Symmetric chi-square distance of the normalised histograms (0–2).")
    mean_grey_before: float
    mean_grey_after: float


class ObjectDetection2D(BaseModel):
    """One detected object."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    label: str
    confidence: float = Field(ge=0, le=1)
    box: PixelBox


class ObjectsMetadata(BaseModel):
    """A detector's objects in one frame, most confident first."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["objects"] = "objects"
    model_id: str
    detections: list[ObjectDetection2D] = Field(min_length=1)


PerceptionMetadata = Annotated[MotionMetadata | SceneChangeMetadata | ObjectsMetadata, Field(discriminator="kind")]
"""What a detector found (its ``kind`` names which)."""


class PerceptionEvent(BaseModel):
    """One detector's finding in one frame of one camera, as published."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: str = Field(description="The detector's kind (motion, scene_change, objects, ...).")
    sensor_id: str
    stamp_ns: int = Field(ge=0, description="Capture time of the frame (monotonic clock).")
    width: int = Field(ge=1)
    height: int = Field(ge=1)
    summary: str = Field(description="One line for people (a log, a dashboard, a reasoner's prompt).")
    metadata: PerceptionMetadata | dict[str, Any]
