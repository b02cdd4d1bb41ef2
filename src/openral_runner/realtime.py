"""Real-time knobs for the tick thread: scheduling policy, CPU affinity, GIL switch interval, memory locking.

Each knob is best effort: one that cannot be applied (no permission, unsupported platform)
is logged as a warning and reported, never fatal.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from typing import Any

import structlog

from openral_core import RealtimeConfig

_log = structlog.get_logger(__name__)

_MCL_CURRENT = 1
_MCL_FUTURE = 2


def apply_realtime(config: RealtimeConfig) -> dict[str, Any]:
    """Apply ``config`` to the calling thread and process.

    Returns:
        A report ``{knob: "applied ..." | "failed: ..."}`` for every requested knob, for
        ``RunResult.metadata``.
    """
    report: dict[str, Any] = {}
    if config.switch_interval_s is not None:
        previous = sys.getswitchinterval()
        sys.setswitchinterval(config.switch_interval_s)
        report["switch_interval_s"] = f"applied {config.switch_interval_s} (was {previous})"
    if config.cpu_affinity is not None:
        report["cpu_affinity"] = _attempt(
            "cpu_affinity", lambda: os.sched_setaffinity(0, set(config.cpu_affinity or ()))
        )
    if config.sched_fifo_priority is not None:
        priority = config.sched_fifo_priority
        report["sched_fifo_priority"] = _attempt(
            "sched_fifo_priority",
            lambda: os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority)),
        )
    if config.lock_memory:
        report["lock_memory"] = _attempt("lock_memory", _mlockall)
    return report


def _attempt(knob: str, apply: Any) -> str:
    try:
        apply()
    except (OSError, AttributeError, ValueError) as exc:
        _log.warning("real-time knob not applied", knob=knob, error=str(exc))
        return f"failed: {exc}"
    return "applied"


def _mlockall() -> None:
    libc_name = ctypes.util.find_library("c")
    if libc_name is None:
        raise OSError("libc not found")
    libc = ctypes.CDLL(libc_name, use_errno=True)
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, os.strerror(errno))
