"""Where each file of a LeRobotDataset v3.0 lives, and the few calls through which the recorder writes them.

One file per episode: episode ``e`` is ``chunk-{e // 1000:03d}/file-{e % 1000:03d}`` under ``data/``,
``meta/episodes/`` and ``videos/<key>/``. ``meta/info.json`` is the commit record: an episode
exists once ``total_episodes`` counts it. The recorder writes its tables and metadata through
:func:`write_file` (videos come from the encoder processes) and puts every file in place through
:func:`move_synced`, both synced.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Final

from openral_core import ROSConfigError

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
_PROBE: Final = "write-probe"


def unsafe_key(key: object) -> str | None:
    """Why ``key`` cannot name a folder inside a dataset (``None``: it can).

    A feature key becomes one path component (``videos/<key>/…``, a replayed frame's file name):
    a separator, ``.``/``..`` or a NUL would let a dataset's metadata write or read elsewhere.
    """
    if not isinstance(key, str) or not key:
        return "it is not a non-empty string"
    if "/" in key or "\\" in key or "\0" in key:
        return "it holds a path separator (or NUL)"
    if key in (".", ".."):
        return f"'{key}' names a folder outside the feature's own"
    return None


def chunk_file(episode_idx: int) -> dict[str, int]:
    """The chunk and file index of ``episode_idx``'s files."""
    return {"chunk_index": episode_idx // CHUNKS_SIZE, "file_index": episode_idx % CHUNKS_SIZE}


def data_file(root: Path, episode_idx: int) -> Path:
    return root / DATA_PATH.format(**chunk_file(episode_idx))


def episodes_file(root: Path, episode_idx: int) -> Path:
    return root / EPISODES_PATH.format(**chunk_file(episode_idx))


def video_file(root: Path, video_key: str, episode_idx: int) -> Path:
    """Episode ``episode_idx``'s video of feature ``video_key``.

    Raises:
        ROSConfigError: ``video_key`` is not a single, safe folder name.
    """
    why = unsafe_key(video_key)
    if why is not None:
        raise ROSConfigError(f"feature {video_key!r} cannot name a video folder: {why}", field="features")
    return root / VIDEO_PATH.format(video_key=video_key, **chunk_file(episode_idx))


def read_info(root: Path) -> dict[str, Any] | None:
    """``meta/info.json`` parsed but not checked (``None`` when there is none); ``meta_reader.read_meta`` checks it.

    Raises:
        ValueError: It is not a JSON object.
    """
    path = root / INFO_PATH
    if not path.exists():
        return None
    info = json.loads(path.read_bytes())
    if not isinstance(info, dict):
        raise ValueError(f"{INFO_PATH} holds a JSON {type(info).__name__}, not an object")
    return info


def dataset_files(root: Path) -> list[Path]:
    """Every file under ``data/``, ``meta/episodes/`` and ``videos/``."""
    found: list[Path] = []
    for top in ("data", "meta/episodes", "videos"):
        base = root / top
        if base.is_dir():
            found.extend(p for p in base.rglob("*") if p.is_file() or p.is_symlink())
    return sorted(found)


def foreign_files(root: Path) -> list[Path]:
    """Every file under ``data/``, ``meta/`` and ``videos/``: what a folder becoming a new dataset must not hold."""
    found: list[Path] = []
    for top in ("data", "meta", "videos"):
        base = root / top
        if base.is_symlink() or base.is_file():
            found.append(base)
        elif base.is_dir():
            found.extend(p for p in base.rglob("*") if not p.is_dir() or p.is_symlink())
    return sorted(found)


def check_writable(root: Path) -> None:
    """Create the dataset and staging folders and write, sync and remove a small file there.

    Raises:
        OSError: The folder cannot be written (read-only, full, not a folder, no permission).
    """
    staging = root / STAGING_DIR
    staging.mkdir(parents=True, exist_ok=True)
    probe = staging / _PROBE
    probe.unlink(missing_ok=True)
    write_file(probe, b"openral")
    probe.unlink()


def write_file(path: Path, data: bytes) -> None:
    """Create ``path`` (never replacing a file) holding ``data``, synced to disk."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "xb") as out:
        out.write(data)
        out.flush()
        os.fsync(out.fileno())


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a synced temporary file and a rename: all or nothing."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.unlink(missing_ok=True)
    try:
        write_file(tmp, data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    sync_dir(path.parent)


def move_synced(src: Path, dst: Path) -> None:
    """Rename a synced file into place and sync the directory that now holds it."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.replace(src, dst)
    sync_dir(dst.parent)


def sync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
