"""The LeRobotDataset v3.0 metadata a commit writes: ``info.json``, the episode row, ``tasks.parquet``, outcome lines.

Pure functions from the recording's state to file contents (bytes or a table); the writer stages
them and :mod:`openral_dataset.commit` moves them into place, ``info.json`` last. Reading them back
(and refusing what cannot be trusted) is :mod:`openral_dataset.meta_reader`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from openral_core import ROSDependencyMissing
from openral_dataset import layout, schema, stats

try:
    import pyarrow as pa
    import pyarrow.parquet as pq
except ImportError as exc:
    raise ROSDependencyMissing("pyarrow", extra="dataset", needed_for="recording datasets") from exc


def info(
    *,
    robot_type: str,
    fps: int,
    features: dict[str, dict[str, Any]],
    episodes: int,
    frames: int,
    tasks: int,
) -> dict[str, Any]:
    """``meta/info.json`` of a dataset holding ``episodes`` episodes, ``frames`` rows and ``tasks`` tasks."""
    has_video = any(spec["dtype"] == "video" for spec in features.values())
    return {
        "codebase_version": layout.CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": episodes,
        "total_frames": frames,
        "total_tasks": tasks,
        "chunks_size": layout.CHUNKS_SIZE,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200,
        "fps": fps,
        "splits": {"train": f"0:{episodes}"},
        "data_path": layout.DATA_PATH,
        "video_path": layout.VIDEO_PATH if has_video else None,
        "features": features,
    }


def episode_row(
    *,
    episode_idx: int,
    task: str,
    frames: int,
    first_index: int,
    fps: int,
    features: dict[str, dict[str, Any]],
    episode_stats: Mapping[str, Mapping[str, np.ndarray]],
) -> pa.Table:
    """The episode's one-row table of ``meta/episodes/``: where its rows and videos are, and its statistics.

    Args:
        first_index: The dataset-wide ``index`` of the episode's first row (the frames committed before it).
    """
    where = layout.chunk_file(episode_idx)
    row: dict[str, Any] = {
        "episode_index": [episode_idx],
        "tasks": [[task]],
        "length": [frames],
        "data/chunk_index": [where["chunk_index"]],
        "data/file_index": [where["file_index"]],
        "dataset_from_index": [first_index],
        "dataset_to_index": [first_index + frames],
    }
    for key in (name for name, spec in features.items() if spec["dtype"] == "video"):
        row[f"videos/{key}/chunk_index"] = [where["chunk_index"]]
        row[f"videos/{key}/file_index"] = [where["file_index"]]
        row[f"videos/{key}/from_timestamp"] = [0.0]
        row[f"videos/{key}/to_timestamp"] = [frames / fps]
    row["meta/episodes/chunk_index"] = [where["chunk_index"]]
    row["meta/episodes/file_index"] = [where["file_index"]]
    for feature, values in episode_stats.items():
        for name, value in values.items():
            row[f"stats/{feature}/{name}"] = [np.asarray(value).tolist()]
    return pa.table(row, schema=schema.episode_schema(features, stats.STAT_NAMES))


def outcome_line(episode_idx: int, *, success: bool | None, repeated_frames: Mapping[str, int]) -> str:
    """The episode's line of ``meta/openral_episodes.jsonl``: its success and each camera's repeated frames."""
    return json.dumps({"episode_index": episode_idx, "success": success, "repeated_frames": dict(repeated_frames)})


def outcomes_bytes(lines: Sequence[str]) -> bytes:
    """``meta/openral_episodes.jsonl`` of ``lines``."""
    return ("\n".join(lines) + "\n").encode("utf-8")


def tasks_parquet_bytes(tasks: dict[str, int]) -> bytes:
    """``meta/tasks.parquet``: a pandas frame indexed by the task string, with a ``task_index`` column."""
    ordered = sorted(tasks.items(), key=lambda item: item[1])
    table = pa.table(
        {"task_index": pa.array([i for _t, i in ordered], pa.int64()), "task": pa.array([t for t, _i in ordered])}
    )
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [
            {"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object", "metadata": None}
        ],
        "columns": [
            {
                "name": "task_index",
                "field_name": "task_index",
                "pandas_type": "int64",
                "numpy_type": "int64",
                "metadata": None,
            },
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": None},
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    return parquet_bytes(table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode("utf-8")}))


def parquet_bytes(table: pa.Table) -> bytes:
    """``table`` as a parquet file in memory: written to disk by :func:`layout.write_file`, synced, like every file."""
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return bytes(sink.getvalue().to_pybytes())
