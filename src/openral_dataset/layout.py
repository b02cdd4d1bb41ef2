"""Where each file of a LeRobotDataset v3.0 lives, and the rule that keeps only committed episodes.

One file per episode: episode ``e`` is ``chunk-{e // 1000:03d}/file-{e % 1000:03d}`` under ``data/``,
``meta/episodes/`` and ``videos/<key>/``. ``meta/info.json`` is the commit record: an episode
exists once ``total_episodes`` counts it, and any file of a later episode is a leftover of an
interrupted commit, removed by :func:`remove_uncommitted`.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any, Final

CODEBASE_VERSION: Final = "v3.0"
CHUNKS_SIZE: Final = 1000
DATA_PATH: Final = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH: Final = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH: Final = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
INFO_PATH: Final = "meta/info.json"
TASKS_PATH: Final = "meta/tasks.parquet"
STATS_PATH: Final = "meta/stats.json"
OUTCOMES_PATH: Final = "meta/openral_episodes.jsonl"
"""What LeRobot's episode rows have no column for: each episode's success and repeated frames, one JSON line each."""
STAGING_DIR: Final = ".openral-staging"
"""Where an episode is written before it is committed: outside ``data/``, ``meta/`` and ``videos/``."""

_FILE = re.compile(r"chunk-(\d{3,})/file-(\d{3,})\.(parquet|mp4)$")


def chunk_file(episode_idx: int) -> dict[str, int]:
    """The chunk and file index of ``episode_idx``'s files."""
    return {"chunk_index": episode_idx // CHUNKS_SIZE, "file_index": episode_idx % CHUNKS_SIZE}


def data_file(root: Path, episode_idx: int) -> Path:
    return root / DATA_PATH.format(**chunk_file(episode_idx))


def episodes_file(root: Path, episode_idx: int) -> Path:
    return root / EPISODES_PATH.format(**chunk_file(episode_idx))


def video_file(root: Path, video_key: str, episode_idx: int) -> Path:
    return root / VIDEO_PATH.format(video_key=video_key, **chunk_file(episode_idx))


def episode_of(path: Path) -> int | None:
    """The episode a dataset file belongs to, from its chunk and file index (``None`` if not such a file)."""
    match = _FILE.search(path.as_posix())
    if match is None:
        return None
    return int(match.group(1)) * CHUNKS_SIZE + int(match.group(2))


def read_info(root: Path) -> dict[str, Any] | None:
    """``meta/info.json``, or ``None`` when the dataset has none yet."""
    path = root / INFO_PATH
    if not path.exists():
        return None
    info: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return info


def dataset_files(root: Path) -> list[Path]:
    """Every episode file under ``data/``, ``meta/episodes/`` and ``videos/``."""
    found: list[Path] = []
    for top in ("data", "meta/episodes", "videos"):
        base = root / top
        if base.is_dir():
            found.extend(p for p in base.rglob("*") if p.is_file())
    return sorted(found)


def remove_uncommitted(root: Path) -> list[Path]:
    """Delete what an interrupted recording left: the staging area and files of uncounted episodes.

    Returns:
        The files removed (the staging area is not listed).
    """
    info = read_info(root)
    committed = 0 if info is None else int(info["total_episodes"])
    removed = []
    for path in dataset_files(root):
        episode = episode_of(path)
        if episode is None or episode >= committed:
            path.unlink()
            removed.append(path)
    staging = root / STAGING_DIR
    if staging.exists():
        for path in sorted(staging.rglob("*"), reverse=True):
            path.rmdir() if path.is_dir() else path.unlink()
        staging.rmdir()
    return removed


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a synced temporary file and a rename: all or nothing."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as out:
        out.write(data)
        out.flush()
        os.fsync(out.fileno())
    os.replace(tmp, path)
    sync_dir(path.parent)


def move_synced(src: Path, dst: Path) -> None:
    """Rename a synced file into place and sync the directory that now holds it."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.replace(src, dst)
    sync_dir(dst.parent)


def sync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def sync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
