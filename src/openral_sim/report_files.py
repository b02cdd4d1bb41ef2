"""The report files ``benchmark run`` writes (``--out``, ``--html``): checked before the run, then written whole.

A report is written to a new file beside its path and renamed over it, so a reader never sees
half a report. A rename replaces whatever is at the path, so that must be a regular file or
nothing: renamed over a FIFO or a device node (``/dev/null``) the report would take the node's
place, and for root that is the system's device. Such a path is refused before the run, and
again just before the rename. So is a symbolic link: never followed (a link planted in a shared
folder must not aim the report at another file), and not silently replaced by the report either.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from openral_core import ROSConfigError, ROSRuntimeError

_SPECIAL_KINDS = (
    (stat.S_ISLNK, "a symbolic link"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def check_output_file(path: Path, *, option: str, example_name: str = "report") -> None:
    """Fail now, before a benchmark runs for minutes, if a report could not be written to ``path``.

    Raises:
        ROSConfigError: ``path`` is a folder or something else that is not a regular file (a
            link, a FIFO, a device, a socket), its folder is missing or not a folder, or it cannot
            be written.
    """
    folder = path.parent
    kind = _special_kind(path)
    if kind is not None:
        problem, hint = f"{path} is {kind}, not a regular file", "name a regular file, or a path where none exists"
    elif path.is_dir():
        problem, hint = f"{path} is a folder", f"give a file name, such as {path / example_name}"
    elif not folder.exists():
        problem, hint = f"the folder {folder} does not exist", "create it first, or choose another path"
    elif not folder.is_dir():
        problem, hint = f"{folder} is not a folder", "choose another path"
    elif not os.access(folder, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        problem, hint = f"cannot write {path}: permission denied", "choose a folder you can write to"
    else:
        return
    raise ROSConfigError(problem, field=option, hint=hint)


def write_whole(path: Path, text: str, *, what: str) -> None:
    """Write ``text`` to ``path``, whole or not at all: a new file of ours renamed over the path.

    Raises:
        ROSRuntimeError: It could not be written, or the path became something other than a
            regular file since it was checked (the message names ``what`` and the path).
    """
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    created = False
    try:
        with partial.open("x", encoding="utf-8") as file:  # "x": a file of ours, which alone may be removed
            created = True
            file.write(text)
        kind = _special_kind(path)
        if kind is not None:
            raise OSError(f"{path} is now {kind}, not a regular file")
        partial.replace(path)
    except OSError as exc:
        if created:
            partial.unlink(missing_ok=True)
        raise ROSRuntimeError(f"cannot write {what} to {path}: {exc}") from exc


def _special_kind(path: Path) -> str | None:
    """What ``path`` itself (a link is not followed) is when it exists and is neither a regular file nor a folder."""
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return None
    return next((kind for is_kind, kind in _SPECIAL_KINDS if is_kind(mode)), None)
