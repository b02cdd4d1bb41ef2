"""``check_dataset``: is this folder a LeRobotDataset v3.0 that LeRobot loads, and do its counters tell the truth?

Uses only pyarrow and PyAV. It checks the layout (every file ``info.json`` promises, nothing it
does not: a staging area or a later episode's file is an orphan that would leak rows into a
load), the counters, index contiguity, the frame grid (``timestamp == frame_index / fps``), each
episode's metadata against its rows and tasks, and every video: one frame per row, frame ``i`` at
``i / fps``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from openral_core import ROSDependencyMissing
from openral_dataset import layout, schema
from openral_dataset.writer import read_tasks

try:
    import av
except ImportError as exc:
    raise ROSDependencyMissing("av", extra="dataset", needed_for="recording datasets") from exc

TIME_TOLERANCE_S = 1e-4
"""How far from ``i / fps`` a video frame may lie: what LeRobot's decoder accepts."""


@dataclass
class CheckReport:
    """What was checked and every problem found (empty: the dataset is sound)."""

    root: Path
    episodes: int = 0
    frames: int = 0
    videos: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def check_dataset(root: Path, *, decode_videos: bool = True) -> CheckReport:
    """Check the dataset at ``root``; every problem is named with the file it is in."""
    report = CheckReport(root)
    problems = report.problems
    try:
        info = layout.read_info(root)
    except ValueError as exc:
        problems.append(f"{layout.INFO_PATH}: not valid JSON ({exc})")
        return report
    if info is None:
        problems.append(f"{layout.INFO_PATH}: missing (no episode was ever committed)")
        return report
    missing = [k for k in _INFO_KEYS if k not in info]
    if missing:
        problems.append(f"{layout.INFO_PATH}: missing keys {missing}")
        return report
    if info["codebase_version"] != layout.CODEBASE_VERSION:
        problems.append(f"{layout.INFO_PATH}: codebase_version {info['codebase_version']!r}, expected 'v3.0'")
    fps = info["fps"]
    if not isinstance(fps, int) or fps < 1:
        problems.append(f"{layout.INFO_PATH}: fps must be a positive integer, got {fps!r}")
        return report
    episodes = int(info["total_episodes"])
    report.episodes = episodes
    video_keys = [k for k, v in info["features"].items() if v.get("dtype") == "video"]

    _check_files(root, episodes, video_keys, problems)
    if (root / layout.STAGING_DIR).exists():
        problems.append(f"{layout.STAGING_DIR}/: an uncommitted episode was left (opening the dataset removes it)")
    if problems:
        return report

    tasks = read_tasks(root)
    if len(tasks) != info["total_tasks"]:
        problems.append(f"{layout.TASKS_PATH}: {len(tasks)} task(s), info.json says {info['total_tasks']}")
    task_of = {index: task for task, index in tasks.items()}
    next_index = 0
    meta_schema: Any = None
    for episode in range(episodes):
        lengths = _check_episode(
            root, episode, fps=fps, first_index=next_index, task_of=task_of, video_keys=video_keys, problems=problems
        )
        if lengths is None:
            return report
        meta_schema = _check_same_schema(root, episode, meta_schema, problems)
        next_index += lengths
        if decode_videos:
            for key in video_keys:
                _check_video(layout.video_file(root, key, episode), lengths, fps, problems)
                report.videos += 1
    report.frames = next_index
    if next_index != info["total_frames"]:
        problems.append(f"{layout.INFO_PATH}: total_frames {info['total_frames']}, the data holds {next_index} rows")
    if info["splits"] != {"train": f"0:{episodes}"}:
        problems.append(f"{layout.INFO_PATH}: splits {info['splits']}, expected {{'train': '0:{episodes}'}}")
    if episodes and not (root / layout.STATS_PATH).exists():
        problems.append(f"{layout.STATS_PATH}: missing (policies normalise with it)")
    return report


_INFO_KEYS = (
    "codebase_version",
    "robot_type",
    "total_episodes",
    "total_frames",
    "total_tasks",
    "chunks_size",
    "data_files_size_in_mb",
    "video_files_size_in_mb",
    "fps",
    "splits",
    "data_path",
    "video_path",
    "features",
)


def _check_files(root: Path, episodes: int, video_keys: list[str], problems: list[str]) -> None:
    expected = set()
    for episode in range(episodes):
        expected.add(layout.data_file(root, episode))
        expected.add(layout.episodes_file(root, episode))
        expected.update(layout.video_file(root, key, episode) for key in video_keys)
    present = set(layout.dataset_files(root))
    for path in sorted(expected - present):
        problems.append(f"{path.relative_to(root)}: missing")
    for path in sorted(present - expected):
        problems.append(f"{path.relative_to(root)}: orphan (not part of a committed episode; LeRobot would load it)")


def _check_episode(
    root: Path,
    episode: int,
    *,
    fps: int,
    first_index: int,
    task_of: dict[int, str],
    video_keys: list[str],
    problems: list[str],
) -> int | None:
    data_path = layout.data_file(root, episode)
    meta_path = layout.episodes_file(root, episode)
    try:
        data = pq.read_table(data_path)
        meta = pq.read_table(meta_path).to_pylist()
    except Exception as exc:  # a parquet without a footer, or not parquet at all
        problems.append(f"episode {episode}: unreadable ({exc})")
        return None
    name = data_path.relative_to(root)
    n = int(data.num_rows)
    nulls = {c: data.column(c).null_count for c in data.column_names if data.column(c).null_count}
    if nulls:
        problems.append(f"{name}: null values {nulls} (LeRobot's batch collation refuses them)")
    columns: dict[str, Any] = {c: data.column(c).to_numpy(zero_copy_only=False) for c in schema.DEFAULT_COLUMNS}
    if not np.array_equal(columns["index"], np.arange(first_index, first_index + n)):
        problems.append(f"{name}: index is not contiguous from {first_index}")
    if not np.array_equal(columns["frame_index"], np.arange(n)):
        problems.append(f"{name}: frame_index does not run 0..{n - 1}")
    if not np.all(columns["episode_index"] == episode):
        problems.append(f"{name}: rows of another episode")
    grid = np.arange(n, dtype=np.float64) / fps
    if not np.allclose(columns["timestamp"].astype(np.float64), grid, atol=TIME_TOLERANCE_S, rtol=0):
        problems.append(f"{name}: timestamp is not frame_index / fps")
    if len(meta) != 1:
        problems.append(f"{meta_path.relative_to(root)}: {len(meta)} rows, expected 1")
        return n
    row = meta[0]
    expect = {
        "episode_index": episode,
        "length": n,
        "dataset_from_index": first_index,
        "dataset_to_index": first_index + n,
    }
    for key, value in expect.items():
        if row.get(key) != value:
            problems.append(f"{meta_path.relative_to(root)}: {key} {row.get(key)}, expected {value}")
    tasks = row.get("tasks") or []
    task_indices = set(columns["task_index"].tolist())
    if len(task_indices) != 1 or task_of.get(task_indices.pop()) not in tasks:
        problems.append(f"{name}: task_index does not name the episode's task {tasks}")
    for key in video_keys:
        end = row.get(f"videos/{key}/to_timestamp")
        if end is None or abs(end - n / fps) > TIME_TOLERANCE_S:
            problems.append(f"{meta_path.relative_to(root)}: videos/{key}/to_timestamp {end}, expected {n / fps}")
    return n


def _check_same_schema(root: Path, episode: int, first: Any, problems: list[str]) -> Any:
    """Every episode's metadata has episode 0's schema: LeRobot concatenates them into one table."""
    path = layout.episodes_file(root, episode)
    found = pq.read_schema(path).remove_metadata()
    if first is not None and not found.equals(first):
        problems.append(f"{path.relative_to(root)}: its schema differs from episode 0's (LeRobot concatenates them)")
    return first if first is not None else found


def _check_video(path: Path, rows: int, fps: int, problems: list[str]) -> None:
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            base = stream.time_base
            if base is None:
                problems.append(f"{path.name}: the video stream has no time base")
                return
            times = [float(frame.pts * base) for frame in container.decode(stream) if frame.pts is not None]
    except Exception as exc:
        problems.append(f"{path.name}: cannot be decoded ({exc})")
        return
    where = path.as_posix()
    if len(times) != rows:
        problems.append(f"{where}: {len(times)} video frames for {rows} rows")
        return
    off = [i for i, t in enumerate(times) if abs(t - i / fps) > TIME_TOLERANCE_S]
    if off:
        problems.append(f"{where}: frame {off[0]} at {times[off[0]]:.6f} s, expected {off[0] / fps:.6f} s")
