"""Opening a folder to record into: refuse what cannot be trusted before touching a file.

- A folder that is a file, or whose metadata ``openral dataset check`` would flag
  (:mod:`openral_dataset.meta_reader`), is refused as it is.
- A new recording needs a folder without ``info.json`` that holds nothing but an interrupted
  first episode of ours (put back); any other file is refused, never deleted.
- A resumed recording needs the dataset's features and rate to be the recording's; then an
  interrupted commit is put back and the dataset's files must agree with its metadata.
- Either way the folder must take a synced file now, before the first tick rather than at the
  first commit.

Every refusal is a ``ROSConfigError`` naming ``field`` (the option or parameter that named the folder).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from openral_core import ROSConfigError
from openral_dataset import commit, layout, meta_reader

_log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class Resumed:
    """What a recording continues from: the committed totals, tasks, outcome lines and merged statistics."""

    episodes: int
    frames: int
    tasks: dict[str, int] = field(default_factory=dict)
    outcomes: list[str] = field(default_factory=list)
    stats: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


def existing(root: Path, *, resume: bool, field: str) -> meta_reader.DatasetMeta | None:
    """The dataset already in ``root``, checked (``None``: there is none yet).

    Raises:
        ROSConfigError: ``root`` is a file, its ``info.json`` cannot be trusted, or it holds a
            dataset and ``resume`` is off.
    """
    if root.exists() and not root.is_dir():
        raise ROSConfigError(f"{root} is a file, not a folder", field=field)
    try:
        found = meta_reader.read_meta(root)
    except meta_reader.MetaError as exc:
        raise ROSConfigError(
            f"cannot open {root}: {exc}",
            field=field,
            hint=f"repair or restore that file, or record into another folder; "
            f"openral dataset check {root} lists every problem",
        ) from None
    if found is not None and not resume:
        raise ROSConfigError(
            f"{root} already holds a dataset of {found.total_episodes} episode(s)",
            field=field,
            hint=f"{'pass --resume' if field.startswith('--') else 'set resume: true'} to add episodes to it, "
            "or choose another folder",
        )
    return found


def check_compatible(
    root: Path, found: meta_reader.DatasetMeta, *, fps: int, features: dict[str, dict[str, Any]], field: str
) -> None:
    """Refuse to resume a dataset recorded at another rate or with other features (dtype, shape, codec, pixels).

    Raises:
        ROSConfigError: What differs.
    """
    problems = []
    if found.fps != fps:
        problems.append(f"fps {found.fps} (this recording: {fps})")
    theirs = {k: _signature(v) for k, v in found.features.items()}
    ours = {k: _signature(v) for k, v in features.items()}
    if theirs != ours:
        missing = sorted(set(ours) - set(theirs))
        extra = sorted(set(theirs) - set(ours))
        changed = sorted(k for k in set(ours) & set(theirs) if ours[k] != theirs[k])
        problems.append(f"features differ (missing {missing}, extra {extra}, changed {changed})")
    if problems:
        raise ROSConfigError(
            f"cannot resume {root}: " + "; ".join(problems),
            field=field,
            hint="record into a new folder, or use the robot, cameras and rate the dataset was recorded with",
        )


def prepare_new(root: Path, *, field: str) -> None:
    """Make ``root`` ready for a first episode: an interrupted one of ours is put back, any other file refused.

    Raises:
        ROSConfigError: ``root`` holds files that are not an openral dataset, or cannot be written.
    """
    with _writing(root, field):
        _report_cleanup(root, commit.recover(root, 0))
    foreign = layout.foreign_files(root)
    if foreign:
        listed = ", ".join(str(p.relative_to(root)) for p in foreign[:3])
        if len(foreign) > 3:
            listed += f" and {len(foreign) - 3} more"
        raise ROSConfigError(
            f"{root} is not an openral dataset: it has no {layout.INFO_PATH} but holds {listed}",
            field=field,
            hint="record into an empty or new folder; openral never deletes files it did not write",
        )
    _check_writable(root, field)


def resume(root: Path, found: meta_reader.DatasetMeta, *, field: str) -> Resumed:
    """Put back an interrupted commit, check the dataset's files against its metadata, and read what goes on.

    Call :func:`check_compatible` first: nothing is touched for a dataset that cannot be resumed.

    Raises:
        ROSConfigError: A file disagrees with the metadata, or ``root`` cannot be written.
    """
    with _writing(root, field):
        _report_cleanup(root, commit.recover(root, found.total_episodes))
    problems = meta_reader.meta_problems(root, found)
    if problems:
        more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
        raise ROSConfigError(
            f"cannot resume {root}: {problems[0]}{more}",
            field=field,
            hint=f"repair or restore those files, or record into another folder; "
            f"openral dataset check {root} lists every problem",
        )
    resumed = Resumed(
        episodes=found.total_episodes,
        frames=found.total_frames,
        tasks=meta_reader.read_tasks(root),
        outcomes=meta_reader.read_outcome_lines(root, found.total_episodes),
        stats=meta_reader.read_stats(root) or {},
    )
    _check_writable(root, field)
    return resumed


def _check_writable(root: Path, field: str) -> None:
    with _writing(root, field):
        layout.check_writable(root)


@contextlib.contextmanager
def _writing(root: Path, field: str) -> Iterator[None]:
    try:
        yield
    except OSError as exc:
        raise ROSConfigError(
            f"cannot write into {root}: {exc.strerror or exc}",
            field=field,
            hint="choose a folder you can write to, on a disk with room",
        ) from exc


def _report_cleanup(root: Path, removed: list[Path]) -> None:
    if removed:
        _log.warning(
            "removed files of an episode that was never committed",
            dataset=str(root),
            files=[str(p.relative_to(root)) for p in removed],
        )


def _signature(feature: dict[str, Any]) -> tuple[Any, ...]:
    """What must match for two recordings to share a dataset: dtype, shape and, for videos, codec and pixels."""
    video = feature.get("info") or {}
    return (feature["dtype"], feature["shape"], video.get("video.codec"), video.get("video.pix_fmt"))
