"""What ``meta/`` (and the file layout it promises) must be before openral reads, resumes or vouches for a dataset.

One set of rules serves ``openral dataset check`` and a resumed recording, which refuses what the
check flags here before it touches a file: ``info.json`` (a JSON object with LeRobot's keys, whole
counters in range, a positive integer ``fps``, feature names that are safe folder names), exactly
the files of its counted episodes under ``data/``, ``meta/episodes/`` and ``videos/``, one
episode row per episode agreeing with the counters, the tasks, the statistics and openral's
outcome lines. Every problem is one line that starts with the file it is in.

This module reads metadata; :mod:`openral_dataset.meta_writer` makes what a commit writes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, TypeGuard

import numpy as np

from openral_core import ROSDependencyMissing
from openral_core.errors import one_line
from openral_dataset import layout, schema, stats

try:
    import pyarrow.parquet as pq
except ImportError as exc:
    raise ROSDependencyMissing("pyarrow", extra="dataset", needed_for="recording datasets") from exc

INFO_KEYS: Final = (
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
_INFO: Final = layout.INFO_PATH


class MetaError(ValueError):
    """A metadata file openral cannot trust; the message starts with the file and names the field."""


@dataclass(frozen=True)
class DatasetMeta:
    """``meta/info.json`` once checked: the counters and features openral relies on."""

    info: dict[str, Any]
    total_episodes: int
    total_frames: int
    total_tasks: int
    fps: int
    features: dict[str, dict[str, Any]]

    @property
    def video_keys(self) -> list[str]:
        return [key for key, spec in self.features.items() if spec["dtype"] == "video"]


def read_meta(root: Path) -> DatasetMeta | None:
    """``meta/info.json`` of ``root``, checked; ``None`` when there is none.

    Raises:
        MetaError: It cannot be read, is not a JSON object, or a key is missing, mistyped or out
            of range (the message names the key).
    """
    path = root / _INFO
    if not path.exists() and not path.is_symlink():
        return None
    try:
        info = json.loads(path.read_bytes())
    except OSError as exc:
        raise MetaError(f"{_INFO}: cannot be read ({exc.strerror or exc})") from None
    except (ValueError, RecursionError) as exc:  # not JSON, not UTF-8, nested too deep
        raise MetaError(f"{_INFO}: not valid JSON ({one_line(str(exc))})") from None
    if not isinstance(info, dict):
        raise MetaError(f"{_INFO}: holds a JSON {_json_type(info)}, not an object")
    missing = [key for key in INFO_KEYS if key not in info]
    if missing:
        raise MetaError(f"{_INFO}: missing keys {missing}")
    if info["codebase_version"] != layout.CODEBASE_VERSION:
        raise MetaError(f"{_INFO}: codebase_version {info['codebase_version']!r}, expected {layout.CODEBASE_VERSION!r}")
    episodes = _whole(info, "total_episodes", minimum=0)
    frames = _whole(info, "total_frames", minimum=0)
    tasks = _whole(info, "total_tasks", minimum=0)
    fps = _whole(info, "fps", minimum=1)
    if info["chunks_size"] != layout.CHUNKS_SIZE:
        raise MetaError(f"{_INFO}: chunks_size {info['chunks_size']!r}, openral's layout has {layout.CHUNKS_SIZE}")
    if info["data_path"] != layout.DATA_PATH:
        raise MetaError(f"{_INFO}: data_path {info['data_path']!r}, expected {layout.DATA_PATH!r}")
    if info["splits"] != {"train": f"0:{episodes}"}:
        raise MetaError(f"{_INFO}: splits {info['splits']!r}, expected {{'train': '0:{episodes}'}}")
    features = _features(info["features"])
    if any(spec["dtype"] == "video" for spec in features.values()) and info["video_path"] != layout.VIDEO_PATH:
        raise MetaError(f"{_INFO}: video_path {info['video_path']!r}, expected {layout.VIDEO_PATH!r}")
    return DatasetMeta(info, episodes, frames, tasks, fps, features)


def meta_problems(root: Path, meta: DatasetMeta) -> list[str]:
    """What is wrong with the dataset's files and ``meta/`` beyond ``info.json`` (empty: nothing).

    Reads the episode rows, tasks, statistics and outcome lines, not the data or the videos.
    """
    problems = layout_problems(root, meta)
    if problems:
        return problems
    rows = episode_rows(root, meta, problems)
    return problems + table_problems(root, meta, rows)


def layout_problems(root: Path, meta: DatasetMeta) -> list[str]:
    """Every file ``info.json`` promises and nothing it does not: a later episode's file would leak into a load."""
    present = set(layout.dataset_files(root))
    episode_files = [p for p in present if p.is_relative_to(root / "meta" / "episodes")]
    if meta.total_episodes > len(episode_files):  # bounds the work a hostile counter can ask for
        return [f"{_INFO}: total_episodes {meta.total_episodes}, but meta/episodes/ holds {len(episode_files)} file(s)"]
    expected = set()
    for episode in range(meta.total_episodes):
        expected.add(layout.data_file(root, episode))
        expected.add(layout.episodes_file(root, episode))
        expected.update(layout.video_file(root, key, episode) for key in meta.video_keys)
    problems = [f"{path.relative_to(root)}: missing" for path in sorted(expected - present)]
    problems += [
        f"{path.relative_to(root)}: orphan (not part of a committed episode; LeRobot would load it)"
        for path in sorted(present - expected)
    ]
    return problems


def episode_rows(root: Path, meta: DatasetMeta, problems: list[str]) -> list[dict[str, Any]]:
    """Each episode's row of ``meta/episodes/``, checked against its index, the counters and episode 0's schema.

    Fewer rows than episodes come back when one cannot be read (the problem says which).
    """
    rows: list[dict[str, Any]] = []
    first_schema: Any = None
    next_index = 0
    for episode in range(meta.total_episodes):
        path = layout.episodes_file(root, episode)
        name = path.relative_to(root)
        try:
            table = pq.read_table(path)
        except Exception as exc:  # a parquet without a footer, or not parquet at all
            problems.append(f"{name}: unreadable ({one_line(str(exc))})")
            return rows
        if table.num_rows != 1:
            problems.append(f"{name}: {table.num_rows} rows, expected 1")
            return rows
        found = table.schema.remove_metadata()
        if first_schema is None:
            first_schema = found
        elif not found.equals(first_schema):
            problems.append(f"{name}: its schema differs from episode 0's (LeRobot concatenates them)")
        row = table.to_pylist()[0]
        length = row.get("length")
        if not _is_whole(length) or length < 0:
            problems.append(f"{name}: length {length!r}, expected a whole number >= 0")
            return rows
        expect = {"episode_index": episode, "dataset_from_index": next_index, "dataset_to_index": next_index + length}
        for key, value in expect.items():
            if row.get(key) != value:
                problems.append(f"{name}: {key} {row.get(key)!r}, expected {value}")
        tasks = row.get("tasks")
        if not isinstance(tasks, list) or not all(isinstance(t, str) for t in tasks):
            problems.append(f"{name}: tasks {tasks!r}, expected a list of task strings")
        next_index += length
        rows.append(row)
    if next_index != meta.total_frames:
        problems.append(f"{_INFO}: total_frames {meta.total_frames}, the episodes in meta/episodes/ hold {next_index}")
    return rows


def table_problems(root: Path, meta: DatasetMeta, rows: list[dict[str, Any]]) -> list[str]:
    """The tasks (against the episode rows), the statistics and the outcome lines."""
    problems: list[str] = []
    try:
        tasks = read_tasks(root)
    except MetaError as exc:
        problems.append(str(exc))
    else:
        _task_problems(root, meta, tasks, rows, problems)
    try:
        if read_stats(root) is None and meta.total_episodes:
            problems.append(f"{layout.STATS_PATH}: missing (policies normalise with it)")
    except MetaError as exc:
        problems.append(str(exc))
    try:
        read_outcome_lines(root, meta.total_episodes)
    except MetaError as exc:
        problems.append(str(exc))
    return problems


def read_tasks(root: Path) -> dict[str, int]:
    """Task string → task index, from ``meta/tasks.parquet`` (empty when there is none).

    Raises:
        MetaError: The file is not a readable table of unique task strings and whole indices.
    """
    path = root / layout.TASKS_PATH
    if not path.exists():
        return {}
    try:
        table = pq.read_table(path)
        names = table.column("task").to_pylist()
        indices = table.column("task_index").to_pylist()
    except Exception as exc:  # a parquet without a footer, not parquet at all, a column missing
        raise MetaError(f"{layout.TASKS_PATH}: unreadable ({one_line(str(exc))})") from None
    if not all(isinstance(name, str) for name in names) or not all(_is_whole(i) and i >= 0 for i in indices):
        raise MetaError(f"{layout.TASKS_PATH}: task must be text and task_index a whole number >= 0")
    if len(set(names)) != len(names) or len(set(indices)) != len(indices):
        raise MetaError(f"{layout.TASKS_PATH}: a task or a task_index appears twice")
    return dict(zip(names, indices, strict=True))


def read_stats(root: Path) -> dict[str, dict[str, np.ndarray]] | None:
    """``meta/stats.json`` as arrays (``None`` when there is none), parsed the way LeRobot's loader parses it.

    Raises:
        MetaError: It is not JSON, or not a map of feature → statistic → array of numbers.
    """
    path = root / layout.STATS_PATH
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_bytes())
    except OSError as exc:
        raise MetaError(f"{layout.STATS_PATH}: cannot be read ({exc.strerror or exc})") from None
    except (ValueError, RecursionError) as exc:
        raise MetaError(f"{layout.STATS_PATH}: not valid JSON ({one_line(str(exc))})") from None
    if not isinstance(data, dict) or not all(isinstance(values, dict) for values in data.values()):
        raise MetaError(f"{layout.STATS_PATH}: must map each feature to its statistics")
    for feature, values in data.items():
        for name, value in values.items():
            if not _array(value):
                raise MetaError(f"{layout.STATS_PATH}: {feature}.{name} is not an array of numbers")
    return stats.from_json(data)


def read_outcome_lines(root: Path, committed: int) -> list[str]:
    """The outcome lines of the first ``committed`` episodes (a line of an episode never committed is dropped).

    Raises:
        MetaError: A line is not a JSON object with a whole ``episode_index``.
    """
    path = root / layout.OUTCOMES_PATH
    if not path.exists():
        return []
    try:
        text = path.read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise MetaError(f"{layout.OUTCOMES_PATH}: cannot be read as UTF-8 text ({one_line(str(exc))})") from None
    lines = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except (ValueError, RecursionError):
            record = None
        index = record.get("episode_index") if isinstance(record, dict) else None
        if not _is_whole(index) or index < 0:
            raise MetaError(f"{layout.OUTCOMES_PATH}: line {number} is not an episode's outcome (JSON, episode_index)")
        if index < committed:
            lines.append(line)
    return lines


# -- the pieces ------------------------------------------------------------------------------


def _task_problems(
    root: Path, meta: DatasetMeta, tasks: dict[str, int], rows: list[dict[str, Any]], problems: list[str]
) -> None:
    if not tasks and meta.total_episodes:
        problems.append(f"{layout.TASKS_PATH}: missing")
        return
    if len(tasks) != meta.total_tasks:
        problems.append(f"{layout.TASKS_PATH}: {len(tasks)} task(s), info.json says {meta.total_tasks}")
    if sorted(tasks.values()) != list(range(len(tasks))):
        problems.append(f"{layout.TASKS_PATH}: task_index does not run 0..{len(tasks) - 1}")
    for episode, row in enumerate(rows):
        unknown = [t for t in row.get("tasks") or [] if t not in tasks]
        if unknown:
            name = layout.episodes_file(root, episode).relative_to(root)
            problems.append(f"{name}: tasks {unknown} are not in {layout.TASKS_PATH}")


def _features(value: object) -> dict[str, dict[str, Any]]:
    if not isinstance(value, dict) or not value:
        raise MetaError(f"{_INFO}: features must be a non-empty object")
    for key, spec in value.items():
        why = layout.unsafe_key(key)
        if why is not None:
            raise MetaError(f"{_INFO}: feature {key!r} cannot name a folder or file: {why}")
        if not isinstance(spec, dict) or not isinstance(spec.get("dtype"), str):
            raise MetaError(f"{_INFO}: features.{key} must be an object with a dtype")
        shape = spec.get("shape")
        if not isinstance(shape, list) or not shape or not all(_is_whole(n) and n >= 0 for n in shape):
            raise MetaError(f"{_INFO}: features.{key}.shape {shape!r}, expected a list of whole numbers")
        if spec["dtype"] == "video" and len(shape) != 3:
            raise MetaError(f"{_INFO}: features.{key}.shape {shape!r}, a video's is [height, width, channels]")
    missing = [name for name in schema.DEFAULT_COLUMNS if name not in value]
    if missing:
        raise MetaError(f"{_INFO}: features lack LeRobot's columns {missing}")
    return value


def _whole(info: dict[str, Any], key: str, *, minimum: int) -> int:
    value = info[key]
    if not _is_whole(value) or value < minimum:
        raise MetaError(f"{_INFO}: {key} must be a whole number >= {minimum}, got {json.dumps(value)}")
    return int(value)


def _is_whole(value: object) -> TypeGuard[int]:
    """An ``int`` that is not a ``bool`` (JSON ``true`` is no count)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _array(value: object) -> bool:
    """Numbers, or lists of them nested to one shape: what ``np.asarray(value, np.float64)`` takes as LeRobot does."""
    if not _numbers(value):
        return False
    try:
        np.asarray(value, dtype=np.float64)
    except ValueError:  # a ragged array
        return False
    return True


def _numbers(value: object) -> bool:
    """A number (not a boolean) or a list of such, nested."""
    if isinstance(value, list):
        return all(_numbers(item) for item in value)
    return isinstance(value, int | float) and not isinstance(value, bool)


def _json_type(value: object) -> str:
    return {list: "array", str: "string", int: "number", float: "number", bool: "boolean"}.get(type(value), "null")
