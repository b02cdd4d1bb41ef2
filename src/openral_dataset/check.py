"""``check_dataset``: is this folder a LeRobotDataset v3.0 that LeRobot loads, and do its counters tell the truth?

Uses only pyarrow and PyAV. ``meta/`` and the file layout are checked by
:func:`openral_dataset.meta_reader.meta_problems` (the rules a resumed recording enforces too): every file
``info.json`` promises and nothing it does not (a later episode's file is an orphan that would
leak rows into a load), the counters, the episode rows, tasks and statistics. Then each episode's
data: index contiguity, the frame grid (``timestamp == frame_index / fps``), its rows against its
episode row, and every video: one frame per row, frame ``i`` at ``i / fps``. A staging area left
by an interrupted recording is a note, not a problem: LeRobot never reads it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from openral_core import ROSDependencyMissing
from openral_core.errors import one_line
from openral_dataset import layout, meta_reader, schema

try:
    import av
except ImportError as exc:
    raise ROSDependencyMissing("av", extra="dataset", needed_for="recording datasets") from exc

TIME_TOLERANCE_S = 1e-4
"""How far from ``i / fps`` a video frame may lie: what LeRobot's decoder accepts."""


@dataclass
class CheckReport:
    """What was checked, every problem found (empty: the dataset is sound) and notes that are no problem."""

    root: Path
    episodes: int = 0
    frames: int = 0
    videos: int = 0
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


def check_dataset(root: Path, *, decode_videos: bool = True) -> CheckReport:
    """Check the dataset at ``root``; every problem is named with the file it is in."""
    report = CheckReport(root)
    problems = report.problems
    if (root / layout.STAGING_DIR).exists():
        report.notes.append(
            f"{layout.STAGING_DIR}/: what an interrupted recording left outside the dataset "
            "(LeRobot never reads it; the next recording into this folder removes it)"
        )
    try:
        info = meta_reader.read_meta(root)
    except meta_reader.MetaError as exc:
        problems.append(str(exc))
        return report
    if info is None:
        problems.append(f"{layout.INFO_PATH}: missing (no episode was ever committed)")
        return report
    report.episodes = info.total_episodes
    problems.extend(meta_reader.layout_problems(root, info))
    if problems:
        return report
    rows = meta_reader.episode_rows(root, info, problems)
    problems.extend(meta_reader.table_problems(root, info, rows))
    try:
        task_of = {index: task for task, index in meta_reader.read_tasks(root).items()}
    except meta_reader.MetaError:
        return report  # reported above
    if len(rows) < info.total_episodes:
        return report  # an episode row cannot be read: the data cannot be checked against it
    next_index = 0
    for episode in range(info.total_episodes):
        length = _check_episode(
            root,
            episode,
            rows[episode],
            fps=info.fps,
            first_index=next_index,
            task_of=task_of,
            video_keys=info.video_keys,
            problems=problems,
        )
        if length is None:
            return report
        next_index += length
        if decode_videos:
            for key in info.video_keys:
                _check_video(layout.video_file(root, key, episode), length, info.fps, problems)
                report.videos += 1
    report.frames = next_index
    if next_index != info.total_frames:
        problems.append(f"{layout.INFO_PATH}: total_frames {info.total_frames}, the data holds {next_index} rows")
    return report


def _check_episode(
    root: Path,
    episode: int,
    row: dict[str, Any],
    *,
    fps: int,
    first_index: int,
    task_of: dict[int, str],
    video_keys: list[str],
    problems: list[str],
) -> int | None:
    """Episode ``episode``'s data against its episode ``row``; its length, or ``None`` if it cannot be read."""
    name = layout.data_file(root, episode).relative_to(root)
    try:
        data = pq.read_table(root / name)
    except Exception as exc:  # a parquet without a footer, or not parquet at all
        problems.append(f"{name}: unreadable ({one_line(str(exc))})")
        return None
    absent = [c for c in schema.DEFAULT_COLUMNS if c not in data.column_names]
    if absent:
        problems.append(f"{name}: columns {absent} are missing")
        return None
    try:
        return _check_rows(
            root,
            episode,
            data,
            row,
            fps=fps,
            first_index=first_index,
            task_of=task_of,
            video_keys=video_keys,
            problems=problems,
        )
    except (TypeError, ValueError) as exc:  # a column of the wrong type
        problems.append(f"{name}: unreadable columns ({one_line(str(exc))})")
        return None


def _check_rows(
    root: Path,
    episode: int,
    data: Any,
    row: dict[str, Any],
    *,
    fps: int,
    first_index: int,
    task_of: dict[int, str],
    video_keys: list[str],
    problems: list[str],
) -> int:
    name = layout.data_file(root, episode).relative_to(root)
    meta_name = layout.episodes_file(root, episode).relative_to(root)
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
    expect = {
        "episode_index": episode,
        "length": n,
        "dataset_from_index": first_index,
        "dataset_to_index": first_index + n,
    }
    for key, value in expect.items():
        if row.get(key) != value:
            problems.append(f"{meta_name}: {key} {row.get(key)}, expected {value}")
    tasks = row.get("tasks") or []
    task_indices = set(columns["task_index"].tolist())
    if len(task_indices) != 1 or task_of.get(task_indices.pop()) not in tasks:
        problems.append(f"{name}: task_index does not name the episode's task {tasks}")
    for key in video_keys:
        end = row.get(f"videos/{key}/to_timestamp")
        if end is None or abs(end - n / fps) > TIME_TOLERANCE_S:
            problems.append(f"{meta_name}: videos/{key}/to_timestamp {end}, expected {n / fps}")
    return n


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
        problems.append(f"{path.as_posix()}: cannot be decoded ({one_line(str(exc))})")
        return
    where = path.as_posix()
    if len(times) != rows:
        problems.append(f"{where}: {len(times)} video frames for {rows} rows")
        return
    off = [i for i, t in enumerate(times) if abs(t - i / fps) > TIME_TOLERANCE_S]
    if off:
        problems.append(f"{where}: frame {off[0]} at {times[off[0]]:.6f} s, expected {off[0] / fps:.6f} s")
