"""Exclusive ownership of a device a HAL drives: one runner per arm.

Two processes writing goals to one servo bus make the arm alternate between two trajectories,
and the second one's torque-off on exit leaves the first one's arm limp. A HAL therefore locks
its device right after opening it, before any byte goes on the wire:

* ``flock(LOCK_EX | LOCK_NB)`` on the open descriptor: a second openral (root included) fails at
  once instead of driving the arm;
* ``TIOCEXCL`` on a serial port: other programs that do not lock (a terminal, another robot
  stack) get ``EBUSY`` from ``open()`` unless they run as root.

The error names the device and, when it can be found (``/proc/locks``, then every process's open
descriptors), the process holding it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import termios
from pathlib import Path

from openral_core.errors import ROSHardwareError


def lock_device(fd: int, path: str, *, exclusive_open: bool = True) -> None:
    """Take exclusive ownership of the open device ``fd`` (``path`` names it in errors).

    Args:
        exclusive_open: Also refuse later ``open()``s of a serial port (``TIOCEXCL``); a HAL
            whose driver opens the port itself after the lock is taken sets it afterwards
            with :func:`refuse_other_opens`.

    Raises:
        ROSHardwareError: Another process holds the device; the message names it when known.
    """
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise device_busy_error(path) from None
    if exclusive_open:
        refuse_other_opens(fd)


def refuse_other_opens(fd: int) -> None:
    """Make a serial port refuse further ``open()``s by non-root programs (``TIOCEXCL``); never raises."""
    if os.isatty(fd):
        with contextlib.suppress(OSError):
            fcntl.ioctl(fd, termios.TIOCEXCL)


def unlock_device(fd: int) -> None:
    """Give the device up again (before closing it); never raises."""
    if os.isatty(fd):
        with contextlib.suppress(OSError):
            fcntl.ioctl(fd, termios.TIOCNXCL)
    with contextlib.suppress(OSError):
        fcntl.flock(fd, fcntl.LOCK_UN)


def device_busy_error(path: str) -> ROSHardwareError:
    """The error for a device another process owns, naming that process when it can be found."""
    holders = [pid for pid in device_holders(path) if pid != os.getpid()]
    who = ", ".join(describe_process(pid) for pid in holders) if holders else "another process"
    return ROSHardwareError(
        f"{path} is in use by {who}: one runner per device (stop the other one first; "
        "two programs on one servo bus would both drive the arm)"
    )


def device_holders(path: str) -> list[int]:
    """Process ids holding ``path`` open: its ``flock`` owners, else every process with it open."""
    try:
        info = os.stat(path)
    except OSError:
        return []
    locked = _flock_owners(os.major(info.st_dev), os.minor(info.st_dev), info.st_ino)
    return locked or _openers(path)


def _flock_owners(major: int, minor: int, inode: int) -> list[int]:
    """Owners of the lock on a file in ``/proc/locks`` (``1: FLOCK ADVISORY WRITE <pid> MM:mm:inode ...``)."""
    owners = []
    try:
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return []
    for line in lines:
        fields = line.split()
        if len(fields) < 6 or fields[1] != "FLOCK":
            continue
        try:
            dev_major, dev_minor, ino = fields[5].split(":")
            if (int(dev_major, 16), int(dev_minor, 16), int(ino)) == (major, minor, inode):
                owners.append(int(fields[4]))
        except ValueError:
            continue
    return owners


def _openers(path: str) -> list[int]:
    """Processes with a descriptor open on the device (scans ``/proc/<pid>/fd``; unreadable ones are skipped)."""
    target = os.path.realpath(path)
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(OSError):
            for fd in (entry / "fd").iterdir():
                with contextlib.suppress(OSError):
                    if os.readlink(fd) == target:
                        found.append(int(entry.name))
                        break
    return found


def describe_process(pid: int) -> str:
    """``pid 1234 (openral deploy --config arm.yaml)``, or just the pid when its command line is unreadable."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return f"pid {pid}"
    args = [part.decode(errors="replace") for part in raw.split(b"\0") if part]
    command = " ".join(args)
    if len(command) > 120:
        command = command[:117] + "..."
    return f"pid {pid} ({command})" if command else f"pid {pid}"
