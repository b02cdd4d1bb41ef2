"""``motion``: what moved since the previous frame of the same camera, counted by cells on the grey image."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core.config import validate_model
from openral_core.perception import MotionMetadata, PixelBox
from openral_perception.frame import DetectorFrame


class MotionParams(BaseModel):
    """``params`` of the ``motion`` detector."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold: float = Field(default=25.0, ge=0, lt=255, description="Grey-level step that counts as a change.")
    cell: int = Field(default=8, ge=1, description="Cell size in pixels.")
    min_cell_fraction: float = Field(default=0.25, gt=0, le=1, description="Changed pixels that make a cell change.")
    min_cells: int = Field(default=2, ge=1, description="Changed cells that make an event.")


class MotionDetector:
    """Motion since the previous frame, by cells.

    A pixel changed when its grey level moved by more than ``threshold``. A ``cell``×``cell``
    block changed when at least ``min_cell_fraction`` of its pixels did; an event needs
    ``min_cells`` changed cells, and its box spans the changed cells only. Sensor noise and
    single hot pixels therefore neither fire nor stretch the box.
    """

    kind = "motion"

    def __init__(self, params: MotionParams | None = None) -> None:
        self.params = params or MotionParams()
        self._previous: dict[str, np.ndarray] = {}

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, base_dir: Path | None = None) -> MotionDetector:
        """Plugin constructor (detector ``motion``); ``params`` are :class:`MotionParams`."""
        return cls(validate_model(MotionParams, dict(params)))

    def detect(self, frame: DetectorFrame) -> MotionMetadata | None:
        """Motion against this sensor's previous frame (``None`` for its first, or after a size change)."""
        grey = frame.grey
        previous = self._previous.get(frame.sensor_id)
        self._previous[frame.sensor_id] = grey
        if previous is None or previous.shape != grey.shape:
            return None
        params = self.params
        changed = np.abs(grey.astype(np.int16) - previous.astype(np.int16)) > params.threshold
        cell = params.cell
        rows, cols = -(-grey.shape[0] // cell), -(-grey.shape[1] // cell)
        padded = np.zeros((rows * cell, cols * cell), dtype=np.uint16)
        padded[: grey.shape[0], : grey.shape[1]] = changed
        counts = padded.reshape(rows, cell, cols, cell).sum(axis=(1, 3))
        cells = counts >= params.min_cell_fraction * cell * cell
        n_cells = int(cells.sum())
        if n_cells < params.min_cells:
            return None
        cell_rows = np.flatnonzero(cells.any(axis=1))
        cell_cols = np.flatnonzero(cells.any(axis=0))
        h, w = grey.shape
        box = PixelBox(
            x0=float(cell_cols[0] * cell),
            y0=float(cell_rows[0] * cell),
            x1=float(min((cell_cols[-1] + 1) * cell, w)),
            y1=float(min((cell_rows[-1] + 1) * cell, h)),
        )
        return MotionMetadata(changed_fraction=n_cells / cells.size, box=box)

    def summarise(self, metadata: MotionMetadata) -> str:
        return describe_motion(metadata)


def describe_motion(metadata: MotionMetadata) -> str:
    """One line for people about a motion event: how much of the view changed, and where."""
    box = metadata.box
    return (
        f"motion over {metadata.changed_fraction:.0%} of the view, "
        f"in ({box.x0:.0f}, {box.y0:.0f})–({box.x1:.0f}, {box.y1:.0f})"
    )
