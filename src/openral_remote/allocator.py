"""Process-wide allocator tuning for processes that move camera-sized messages: an explicit, deliberate call.

Nothing in ``openral_remote`` calls it on its own (opening a session does not): it changes how the
whole process allocates, so the process's entry point decides. ``openral serve`` calls it, and so
does ``openral deploy`` when its skill is a remote policy. Needs no Zenoh.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable
from typing import Final

_M_TRIM_THRESHOLD: Final = -1
_M_MMAP_THRESHOLD: Final = -3
MMAP_THRESHOLD_BYTES: Final = 64 << 20
TRIM_THRESHOLD_BYTES: Final = 256 << 20


def _mallopt() -> Callable[[int, int], int] | None:
    """glibc's ``mallopt``; ``None`` where the C library is not glibc."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        mallopt: Callable[[int, int], int] = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return None
    return mallopt


@functools.cache
def keep_message_memory() -> bool:
    """Keep freed large buffers in the process (glibc) instead of returning them to the kernel after each message.

    A camera observation is about a megabyte. By default glibc serves such a block with a fresh
    ``mmap`` (or trims a thread arena's top) and gives it back on free, so every message pays
    a few hundred page faults on both ends (measured here: 1.2 ms of a 6 ms round trip). Raising
    the mmap and trim thresholds, as real-time guides advise, makes the blocks reused. The process
    keeps up to about 256 MB of freed memory instead of returning it.

    Once per process (later calls return the first answer).

    Returns:
        Whether the thresholds were set (``False`` where the C library is not glibc).
    """
    mallopt = _mallopt()
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )


__all__ = ["keep_message_memory"]
