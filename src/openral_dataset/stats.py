"""Feature statistics as LeRobot reads them: min, max, mean, std, count and five quantiles.

Per episode they are computed from the episode's values (cameras from a subsample of frames and
pixels, scaled to 0..1, one value per channel); the dataset's are merged from the episodes'
with count weights, so committing an episode never re-reads the earlier ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Final

import numpy as np

from openral_core import SensorFrame

QUANTILES: Final = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
STAT_NAMES: Final = ("min", "max", "mean", "std", "count", *QUANTILES)
IMAGE_SAMPLE_FRAMES: Final = 32
"""Frames per episode (at least, at most twice as many) that camera statistics are computed from."""
IMAGE_SAMPLE_STRIDE: Final = 8
"""Every n-th pixel in each direction of a sampled frame."""


def vector_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """Statistics of a ``[frames, n]`` (or ``[frames]``) array, per column, over its finite values.

    A value a tick did not have is recorded as NaN (a withheld action, a camera before its first
    frame); it is left out rather than turning the column's statistics into NaN. A column with
    no finite value at all has NaN statistics.
    """
    data = np.asarray(values, dtype=np.float64)
    if data.ndim == 1:
        data = data[:, None]
    columns = data.shape[1]
    out = {name: np.full(columns, np.nan) for name in ("min", "max", "mean", "std", *QUANTILES)}
    for column in range(columns):
        finite = data[:, column][np.isfinite(data[:, column])]
        if finite.size == 0:
            continue
        out["min"][column] = finite.min()
        out["max"][column] = finite.max()
        out["mean"][column] = finite.mean()
        out["std"][column] = finite.std()
        for name, q in QUANTILES.items():
            out[name][column] = np.quantile(finite, q)
    out["count"] = np.array([len(data)])
    return out


class FrameSample:
    """A camera's frames for its episode statistics: every n-th frame, every ``IMAGE_SAMPLE_STRIDE``-th pixel.

    n starts at 1 and doubles (dropping every other frame kept) whenever :data:`IMAGE_SAMPLE_FRAMES`
    twice over are held, so an episode of any length keeps between that many and twice as many.
    """

    def __init__(self) -> None:
        self.frames: list[np.ndarray] = []
        """The sampled ``[h, w, 3]`` uint8 RGB copies, as the video decodes them."""
        self._stride = 1

    def add(self, frame: SensorFrame, frame_index: int) -> None:
        """Keep ``frame`` (row ``frame_index`` of the episode) if it falls on the stride.

        Raises:
            ValueError: The frame has no 8-bit colour view (see :meth:`SensorFrame.as_rgb`).
        """
        if frame_index % self._stride:
            return
        step = IMAGE_SAMPLE_STRIDE
        self.frames.append(np.ascontiguousarray(frame.as_rgb()[::step, ::step]))
        if len(self.frames) >= 2 * IMAGE_SAMPLE_FRAMES:
            del self.frames[1::2]
            self._stride *= 2


def image_stats(frames: Sequence[np.ndarray], total_frames: int) -> dict[str, np.ndarray]:
    """Per-channel statistics (shape ``[3, 1, 1]``, values 0..1) of sampled, subsampled ``[h, w, 3]`` uint8 frames."""
    pixels = np.concatenate([f.reshape(-1, 3) for f in frames], axis=0).astype(np.float64)
    pixels /= 255.0
    stats = vector_stats(pixels)
    shaped = {name: value.reshape(3, 1, 1) for name, value in stats.items() if name != "count"}
    shaped["count"] = np.array([total_frames])
    return shaped


def merge_stats(parts: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Merge per-episode statistics of one feature with count weights (quantiles: weighted mean).

    An element that is NaN in one episode (no finite value there) is merged from the others.
    """
    counts = np.array([float(p["count"][0]) for p in parts])
    means = np.stack([p["mean"] for p in parts])
    shape = (-1,) + (1,) * (means.ndim - 1)
    present = np.isfinite(means)
    weights = np.where(present, counts.reshape(shape), 0.0)
    total = weights.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(total > 0, weights / np.where(total > 0, total, 1.0), 0.0)

        def weighted(name: str) -> np.ndarray:
            values = np.nan_to_num(np.stack([p[name] for p in parts]), nan=0.0)
            return np.where(total > 0, (w * values).sum(axis=0), np.nan)

        mean = weighted("mean")
        stds = np.nan_to_num(np.stack([p["std"] for p in parts]), nan=0.0)
        second = np.where(total > 0, (w * (stds**2 + np.nan_to_num(means) ** 2)).sum(axis=0), np.nan)
        merged = {
            "min": np.fmin.reduce(np.stack([p["min"] for p in parts]), axis=0),
            "max": np.fmax.reduce(np.stack([p["max"] for p in parts]), axis=0),
            "mean": mean,
            "std": np.sqrt(np.maximum(second - mean**2, 0.0)),
            "count": np.array([int(counts.sum())]),
        }
        for name in QUANTILES:
            merged[name] = weighted(name)
    return merged


def to_json(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    """Statistics as nested lists for ``meta/stats.json``."""
    return {feature: {name: np.asarray(v).tolist() for name, v in values.items()} for feature, values in stats.items()}


def from_json(data: dict[str, dict[str, Any]]) -> dict[str, dict[str, np.ndarray]]:
    """The inverse of :func:`to_json`."""
    return {feature: {name: np.asarray(v) for name, v in values.items()} for feature, values in data.items()}
