"""Real-time knobs for the tick thread: scheduling policy, CPU affinity, GIL switch interval, memory locking.

Each knob is best effort: one that cannot be applied (no permission, unsupported platform)
is logged as a warning and reported, never fatal. Everything applied is undone by
``RealtimeSettings.restore()``, so a runner leaves its thread as it found it.

Apply the knobs *after* starting capture and physics threads: a thread inherits its creator's
scheduling policy, and background work at real-time priority would compete with the tick it
is meant to stay out of the way of. Threads that may be started later from a real-time
thread call ``leave_realtime_scheduling()`` first.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import structlog

from openral_core import RealtimeConfig

_log = structlog.get_logger(__name__)

_MCL_CURRENT = 1
_MCL_FUTURE = 2


@dataclass
class RealtimeSettings:
    """What ``apply_realtime`` did: a report per knob and how to undo it."""

    report: dict[str, Any] = field(default_factory=dict)
    _undo: list[Callable[[], None]] = field(default_factory=list)

    def restore(self) -> None:
        """Undo every applied knob, newest first. Idempotent; failures are logged."""
        while self._undo:
            undo = self._undo.pop()
            try:
                undo()
            except (OSError, ValueError) as exc:
                _log.warning("could not restore a real-time knob", error=str(exc))


def apply_realtime(config: RealtimeConfig) -> RealtimeSettings:
    """Apply ``config`` to the calling thread and process."""
    settings = RealtimeSettings()
    if config.switch_interval_s is not None:
        previous = sys.getswitchinterval()
        sys.setswitchinterval(config.switch_interval_s)
        settings.report["switch_interval_s"] = f"applied {config.switch_interval_s} (was {previous})"
        settings._undo.append(lambda: sys.setswitchinterval(previous))
    if config.cpu_affinity is not None:
        cpus = set(config.cpu_affinity)
        before = os.sched_getaffinity(0)
        if _attempt(settings, "cpu_affinity", lambda: os.sched_setaffinity(0, cpus)):
            settings._undo.append(lambda: os.sched_setaffinity(0, before))
    if config.sched_fifo_priority is not None:
        priority = config.sched_fifo_priority
        policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
        if _attempt(
            settings,
            "sched_fifo_priority",
            lambda: os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority)),
        ):
            settings._undo.append(lambda: os.sched_setscheduler(0, policy, param))
    if config.lock_memory and _attempt(
        settings, "lock_memory", lambda: _libc_call("mlockall", _MCL_CURRENT | _MCL_FUTURE)
    ):
        settings._undo.append(lambda: _libc_call("munlockall"))
    return settings


def leave_realtime_scheduling() -> None:
    """Give the calling thread the ordinary policy (``SCHED_OTHER``) if it inherited a real-time one.

    Lowering a policy needs no privilege.
    """
    if not hasattr(os, "sched_getscheduler"):  # pragma: no cover - not Linux
        return
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError as exc:  # pragma: no cover - lowering is always permitted on Linux
        _log.warning("could not leave real-time scheduling", error=str(exc))


def _attempt(settings: RealtimeSettings, knob: str, apply: Callable[[], object]) -> bool:
    try:
        apply()
    except (OSError, AttributeError, ValueError) as exc:
        _log.warning("real-time knob not applied", knob=knob, error=str(exc))
        settings.report[knob] = f"failed: {exc}"
        return False
    settings.report[knob] = "applied"
    return True


def _libc_call(name: str, *args: int) -> None:
    libc_name = ctypes.util.find_library("c")
    if libc_name is None:
        raise OSError("libc not found")
    libc = ctypes.CDLL(libc_name, use_errno=True)
    if getattr(libc, name)(*args) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, os.strerror(errno))
