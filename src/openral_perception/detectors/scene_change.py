"""``scene_change``: an abrupt change of the whole view, by grey histograms against the previous frame's."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core.config import validate_model
from openral_core.perception import SceneChangeMetadata
from openral_perception.frame import DetectorFrame


class SceneChangeParams(BaseModel):
    """``params`` of the ``scene_change`` detector."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold: float = Field(default=0.5, gt=0, le=2, description="Chi-square distance (0–2) that is a change.")
    bins: int = Field(default=32, ge=2, le=256, description="Histogram bins over the full 0–255 range.")


class SceneChangeDetector:
    """An abrupt change of the scene: the grey histogram against the previous frame's.

    Histograms of ``bins`` bins over the full 0–255 range, normalised; the distance is the
    symmetric chi-square ``sum((p - q)^2 / (p + q))``, from 0 (same) to 2 (disjoint). Above
    ``threshold`` is an event. A uniform 200-grey frame turning 240 is a change of 2.
    """

    kind = "scene_change"

    def __init__(self, params: SceneChangeParams | None = None) -> None:
        self.params = params or SceneChangeParams()
        self._previous: dict[str, tuple[np.ndarray, float]] = {}

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, base_dir: Path | None = None) -> SceneChangeDetector:
        """Plugin constructor (detector ``scene_change``); ``params`` are :class:`SceneChangeParams`."""
        return cls(validate_model(SceneChangeParams, dict(params)))

    def histogram(self, grey: np.ndarray) -> np.ndarray:
        """The normalised histogram of a grey frame."""
        bins = self.params.bins
        index = (grey.astype(np.uint32) * bins) >> 8
        counts = np.bincount(index.ravel(), minlength=bins).astype(np.float64)
        return counts / max(1.0, float(counts.sum()))

    def detect(self, frame: DetectorFrame) -> SceneChangeMetadata | None:
        """A scene change against this sensor's previous frame (``None`` for its first)."""
        grey = frame.grey
        current = (self.histogram(grey), float(grey.mean()))
        previous = self._previous.get(frame.sensor_id)
        self._previous[frame.sensor_id] = current
        if previous is None:
            return None
        p, q = previous[0], current[0]
        total = p + q
        present = total > 0
        distance = float(((p[present] - q[present]) ** 2 / total[present]).sum())
        if distance <= self.params.threshold:
            return None
        return SceneChangeMetadata(distance=distance, mean_grey_before=previous[1], mean_grey_after=current[1])

    def summarise(self, metadata: SceneChangeMetadata) -> str:
        return (
            f"scene changed (distance {metadata.distance:.2f}; mean grey "
            f"{metadata.mean_grey_before:.0f} -> {metadata.mean_grey_after:.0f})"
        )
