"""The episode under way: its rows in memory, its cameras' encoders and statistics samples, in a staging folder.

:class:`StagedEpisode` holds what one episode has recorded until the writer commits it (or throws
it away); nothing in it is part of the dataset until :mod:`openral_dataset.commit` moves its files
into place. :class:`EpisodeSummary` is what is told about an episode afterwards.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from openral_core import ROSDependencyMissing, ROSRuntimeError, SensorFrame
from openral_dataset import schema, stats
from openral_dataset.video import StreamingVideoEncoder

try:
    import pyarrow as pa
except ImportError as exc:
    raise ROSDependencyMissing("pyarrow", extra="dataset", needed_for="recording datasets") from exc

_log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class EpisodeSummary:
    """What one committed (or discarded) episode held."""

    episode_idx: int
    frames: int
    task: str
    committed: bool
    repeated_frames: dict[str, int]
    close_s: float = 0.0


@dataclass
class StagedEpisode:
    """One episode being recorded, in ``folder`` (outside the dataset's own folders).

    Attributes:
        rows: Column name → the values of every row so far (the data parquet's columns).
        encoders: Each camera's video encoder, once the camera's size is known.
        unsized: Rows recorded per camera before its size was known (black frames go in for them).
        failed: An encoder fell behind under the ``fail`` policy: the episode cannot be kept.
    """

    idx: int
    task: str
    task_index: int
    folder: Path
    rows: dict[str, list[Any]]
    encoders: dict[str, StreamingVideoEncoder] = field(default_factory=dict)
    samples: dict[str, stats.FrameSample] = field(default_factory=dict)
    unsized: dict[str, int] = field(default_factory=dict)
    failed: bool = False
    long_warned: bool = False

    @property
    def frames(self) -> int:
        """Rows recorded so far."""
        return len(self.rows["frame_index"])

    @property
    def repeated_frames(self) -> dict[str, int]:
        """Each camera's video frames repeated so far (no frame came, or its encoder fell behind)."""
        return {camera: encoder.repeated for camera, encoder in self.encoders.items()}

    def sample(self, camera: str, frame: SensorFrame, frame_index: int) -> None:
        """Offer an encoded frame to the camera's statistics sample."""
        self.samples.setdefault(camera, stats.FrameSample()).add(frame, frame_index)

    def append(self, row: Mapping[str, Any], absent: Mapping[str, Any], *, fps: int) -> None:
        """Append ``row`` (a column missing or ``None`` takes its ``absent`` value); warn once when too long."""
        if self.frames / fps >= schema.TIMESTAMP_EXACT_S and not self.long_warned:
            self.long_warned = True
            _log.warning(
                "episode longer than float32 timestamps resolve within LeRobot's tolerance; end episodes sooner",
                episode=self.idx,
                limit_s=schema.TIMESTAMP_EXACT_S,
            )
        for name, values in self.rows.items():
            value = row.get(name)
            values.append(absent[name] if value is None else value)

    def finish_videos(self, cameras: Sequence[schema.CameraSpec]) -> None:
        """Finish every camera's video.

        Raises:
            ROSRuntimeError: A camera delivered no frame, or its video has not one frame per row.
        """
        for cam in cameras:
            if cam.sensor_id not in self.encoders:
                raise ROSRuntimeError(f"camera {cam.sensor_id} delivered no frame in episode {self.idx}")
            written = self.encoders[cam.sensor_id].finish()
            if written != self.frames:
                raise ROSRuntimeError(f"camera {cam.sensor_id}: {written} video frames for {self.frames} rows")

    def abort_videos(self) -> None:
        """Stop every encoder without finishing its video (one that already failed may be gone)."""
        for encoder in self.encoders.values():
            try:
                encoder.abort()
            except Exception as exc:  # an encoder that failed may be gone already
                _log.debug("aborting an encoder failed", episode=self.idx, error=str(exc))

    def discard(self) -> None:
        """Throw the episode away: its encoders stopped, its staging folder removed."""
        self.abort_videos()
        shutil.rmtree(self.folder, ignore_errors=True)

    def statistics(
        self, features: dict[str, dict[str, Any]], table: pa.Table, cameras: Sequence[schema.CameraSpec]
    ) -> dict[str, dict[str, np.ndarray]]:
        """Per-feature statistics of the episode: columns from its data ``table``, cameras from their samples."""
        out = {}
        for name in schema.stat_features(features):
            if name in table.column_names:
                values = np.asarray(table.column(name).to_pylist(), dtype=np.float64)
                out[name] = stats.vector_stats(values)
        for cam in cameras:
            # No sample means the video holds only black filler frames: their statistics are zeros.
            sample = self.samples.get(cam.sensor_id)
            frames = sample.frames if sample is not None and sample.frames else [np.zeros((1, 1, 3), np.uint8)]
            out[schema.video_key(cam.sensor_id)] = stats.image_stats(frames, len(table))
        return out
