"""A policy server's Zenoh id: the same at every restart on this host, never the same for two live servers.

Robots pin the id of the server they first reached and take a restarted server back only if it
presents that id again. Two live sessions with one id cannot be told apart: Zenoh refuses the
second one's links, so neither sees the other's liveliness token, and the check that keeps a
second server off a live key sees nothing. So an id is neither derived from the key alone nor
drawn afresh at each start: each server claims a slot of its key in a per-user state folder
(``$XDG_STATE_HOME/openral/serve``, default ``~/.local/state/openral/serve``) and holds an
exclusive lock on the slot's file while it runs. A restart takes the first slot, and its id,
again; a second server of the key on this host finds that slot locked and takes the next, whose
id is another. Ids are random (128 bits), so servers on different hosts do not share one either.

An id given by hand (``--zenoh-id``) is locked the same way, so two servers of this host cannot
both take it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import secrets
from pathlib import Path

from openral_core import ROSConfigError
from openral_remote.config import ZENOH_ID
from openral_remote.keys import PolicyKeys

__all__ = ["MAX_SLOTS", "ServerIdentity", "claim_server_id", "state_folder"]

MAX_SLOTS = 64
"""Servers of one key on one host at once (each with its own endpoint; connected ones refuse each other)."""

_ID_BYTES = 64
"""What a slot file holds at most: one id and a line break."""


class ServerIdentity:
    """A claimed Zenoh id, held (its file locked) until closed or the process ends. A context manager.

    Attributes:
        zid: The id.
        path: The locked file.
    """

    def __init__(self, zid: str, path: Path, fd: int) -> None:
        self.zid = zid
        self.path = path
        self._fd: int | None = fd

    def __enter__(self) -> ServerIdentity:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Give the id up (another server of this host may take it). Idempotent."""
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases its lock
            self._fd = None


def state_folder() -> Path:
    """Where servers keep their ids: ``$XDG_STATE_HOME/openral/serve`` (default ``~/.local/state/...``)."""
    base = os.environ.get("XDG_STATE_HOME") or "~/.local/state"
    return Path(base).expanduser() / "openral" / "serve"


def claim_server_id(keys: PolicyKeys, zid: str | None = None, *, folder: Path | None = None) -> ServerIdentity:
    """The Zenoh id of a server of ``keys``: ``zid`` if given, else the first free slot's (made on first use).

    Raises:
        ROSConfigError: The state folder cannot be written, ``zid`` is held by another server of
            this host, or every slot of the key is.
    """
    where = folder or state_folder()
    _make_folder(where)
    if zid is not None:
        if not re.fullmatch(ZENOH_ID, zid):
            raise ROSConfigError(
                f"{zid!r} is not a Zenoh id", field="--zenoh-id", hint="lowercase hex, 1 to 32 digits, no leading 0"
            )
        path = where / f"zid-{zid}.lock"
        fd = _lock(path)
        if fd is None:
            raise ROSConfigError(
                f"Zenoh id {zid} is held by another policy server on this host ({path} is locked)",
                field="--zenoh-id",
                hint="two live servers with one id cannot be told apart: give another id, or leave it out",
            )
        return ServerIdentity(zid, path, fd)
    stem = f"{keys.robot}+{keys.policy}"  # '+' is in no key segment: one file name per key
    for slot in range(MAX_SLOTS):
        path = where / f"{stem}.{slot}.id"
        fd = _lock(path)
        if fd is not None:
            return ServerIdentity(_stored_or_new(fd, path), path, fd)
    raise ROSConfigError(
        f"{MAX_SLOTS} servers of {keys.prefix} already run on this host (every id slot in {where} is locked)",
        hint="stop one of them first",
    )


def _make_folder(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError as exc:
        raise ROSConfigError(
            f"cannot keep the server's Zenoh id in {folder}: {exc.strerror or exc}",
            field="XDG_STATE_HOME",
            hint="point XDG_STATE_HOME at a writable folder, or give --zenoh-id",
        ) from None


def _lock(path: Path) -> int | None:
    """An open descriptor on ``path`` holding its exclusive lock; ``None`` if another process holds it."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    except OSError as exc:
        raise ROSConfigError(
            f"cannot keep the server's Zenoh id in {path}: {exc.strerror or exc}",
            field="XDG_STATE_HOME",
            hint="point XDG_STATE_HOME at a writable folder, or give --zenoh-id",
        ) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def _stored_or_new(fd: int, path: Path) -> str:
    """The id in the locked slot file, or a new one written there (an empty or damaged file)."""
    stored = os.pread(fd, _ID_BYTES, 0).decode("ascii", "replace").strip()
    if re.fullmatch(ZENOH_ID, stored):
        return stored
    zid = format(secrets.randbits(128) | (1 << 127), "032x")  # top bit set: 32 digits, no leading 0
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{zid}\n".encode("ascii"), 0)
        os.fsync(fd)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.close(fd)
        raise ROSConfigError(
            f"cannot keep the server's Zenoh id in {path}: {exc.strerror or exc}",
            field="XDG_STATE_HOME",
            hint="point XDG_STATE_HOME at a writable folder, or give --zenoh-id",
        ) from None
    return zid
