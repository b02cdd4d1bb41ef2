"""An episode moved into its dataset as one step: a journal that proves which files are the recorder's, and the undo.

Everything a commit adds or replaces (the episode's data, episode row and videos; the new
``tasks.parquet``, ``stats.json``, outcome lines and ``info.json``) is first written and synced in
the episode's staging folder. Before the first file moves, a journal there names each
destination with the identity (device, inode, size, modification time) of the staged file that
will land on it, and keeps a hard link to each metadata file about to be replaced. ``info.json``
moving into place, last, is the commit. Until then :func:`undo` puts the dataset back as it was:
after a failure in this process, or after a crash the next time the dataset is opened
(:func:`recover`). It deletes a file only when its identity is the one the journal recorded, so a
file the recorder did not write is never touched.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import structlog

from openral_core import ROSRuntimeError
from openral_dataset import layout

_log = structlog.get_logger(__name__)

JOURNAL: Final = "journal.json"
_BACKUPS: Final = "replaced"


@dataclass(frozen=True)
class Move:
    """One staged file and where it goes; ``replaces``: it may take the place of an existing file (metadata)."""

    staged: Path
    dest: Path
    replaces: bool = False


def apply(root: Path, folder: Path, episode_idx: int, moves: Sequence[Move]) -> None:
    """Move ``moves`` into ``root`` in order; the last (``meta/info.json``) commits the episode.

    On failure nothing is put back here: :func:`discard` does that (and keeps the journal if it cannot).

    Raises:
        ROSRuntimeError: A new episode file's place is taken already (nothing was moved).
        OSError: A write or rename failed before the commit.
    """
    for move in moves:
        if not move.replaces and (move.dest.exists() or move.dest.is_symlink()):
            raise ROSRuntimeError(
                f"{move.dest} exists already: the recorder will not replace a file it did not write "
                f"(move it out of {root})"
            )
    entries = []
    for number, move in enumerate(moves):
        entry: dict[str, Any] = {"dest": move.dest.relative_to(root).as_posix(), "id": _identity(move.staged)}
        if move.replaces and move.dest.exists():
            backup = folder / _BACKUPS / str(number)
            _keep(move.dest, backup)
            entry["backup"] = backup.relative_to(folder).as_posix()
        entries.append(entry)
    layout.write_atomic(folder / JOURNAL, json.dumps({"episode_index": episode_idx, "moves": entries}).encode())
    for move in moves[:-1]:
        layout.move_synced(move.staged, move.dest)
    last = moves[-1]
    try:
        layout.move_synced(last.staged, last.dest)
    except Exception:
        if not _is(last.dest, entries[-1]["id"]):
            raise
        _log.warning("episode committed, but syncing its folder failed", dataset=str(root), episode=episode_idx)


def discard(root: Path, folder: Path, *, committed: int) -> list[Path]:
    """Undo ``folder``'s commit unless it was committed, then remove the folder (kept if the undo fails).

    Returns:
        The episode files removed.
    """
    removed = undo(root, folder, committed=committed)
    shutil.rmtree(folder)
    return removed


def undo(root: Path, folder: Path, *, committed: int) -> list[Path]:
    """Put back what the journal in ``folder`` moved into ``root``, unless its episode was committed.

    The episode counts as committed when it is below ``committed`` (``info.json``'s count) or when
    ``info.json`` is the one the journal staged. Idempotent: a crash part-way is undone again later.

    Returns:
        The files of the episode it removed.
    """
    journal = _read_journal(folder)
    if journal is None:
        return []  # no journal: nothing was moved yet
    index, entries = journal
    if index < committed or (entries and _is(root / entries[-1]["dest"], entries[-1]["id"])):
        return []
    removed = []
    for entry in reversed(entries):
        dest = root / entry["dest"]
        if _is(dest, entry["id"]):
            dest.unlink()
            removed.append(dest)
        backup = entry.get("backup")
        if backup is not None and (folder / backup).exists():
            if dest.exists() and not dest.samefile(folder / backup):
                _log.warning("left a file changed since the interrupted commit", file=str(dest))
                continue
            os.replace(folder / backup, dest)
    return removed


def recover(root: Path, committed: int) -> list[Path]:
    """Undo every commit an interrupted recording left in the staging area, then remove the area.

    Returns:
        The episode files removed (the staging area is not listed).
    """
    staging = root / layout.STAGING_DIR
    if not staging.is_dir():
        return []
    removed = []
    for folder in sorted(staging.iterdir()):
        if folder.is_dir() and not folder.is_symlink():
            removed += discard(root, folder, committed=committed)
    shutil.rmtree(staging)
    return removed


def _keep(path: Path, backup: Path) -> None:
    """A second name for ``path`` in the staging folder (a hard link needs no room on a full disk; else a copy)."""
    backup.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(path, backup)
    except OSError:  # a file system without hard links
        layout.write_file(backup, path.read_bytes())


def _identity(path: Path) -> list[int]:
    st = path.stat()
    return [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns]


def _is(path: Path, identity: object) -> bool:
    """Whether ``path`` is the very file whose identity the journal recorded."""
    try:
        return not path.is_symlink() and _identity(path) == identity
    except OSError:
        return False


def _read_journal(folder: Path) -> tuple[int, list[dict[str, Any]]] | None:
    """The journal's episode and moves; ``None`` if there is none (a torn one is never renamed into place)."""
    path = folder / JOURNAL
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_bytes())
        index = data["episode_index"]
        entries = [dict(e) for e in data["moves"]]
        for entry in entries:
            dest = Path(entry["dest"])
            if dest.is_absolute() or ".." in dest.parts or not isinstance(entry["id"], list):
                raise ValueError(entry["dest"])
            backup = entry.get("backup")
            if backup is not None and (Path(backup).is_absolute() or ".." in Path(backup).parts):
                raise ValueError(backup)
        if not isinstance(index, int):
            raise ValueError(index)
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as exc:
        _log.warning("ignored a commit journal openral cannot read", journal=str(path), error=str(exc))
        return None
    return index, entries
