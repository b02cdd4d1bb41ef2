"""Opening a Zenoh session from a :class:`~openral_remote.config.ZenohConfig`, errors translated."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import json
from typing import Any

from openral_core import ROSConfigError, ROSDependencyMissing, ROSRuntimeError
from openral_remote.config import ZenohConfig

try:
    import zenoh
except ImportError as exc:
    raise ROSDependencyMissing("zenoh", extra="remote", needed_for="remote inference over Zenoh") from exc


def zenoh_config(config: ZenohConfig) -> Any:
    """The ``zenoh.Config`` of ``config``."""
    settings = zenoh.Config()
    for path, value in config.settings().items():
        try:
            settings.insert_json5(path, json.dumps(value))
        except Exception as exc:  # zenoh raises its own ZError for a bad value
            raise ROSConfigError(f"zenoh refused {path}={value!r}: {exc}", field="zenoh") from exc
    return settings


_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


@functools.cache
def keep_message_memory() -> bool:
    """Keep freed large buffers in the process (glibc) instead of returning them to the kernel after each message.

    A camera observation is about a megabyte. By default glibc serves such a block with a fresh
    ``mmap`` (or trims a thread arena's top) and gives it back on free, so every message pays
    a few hundred page faults on both ends (measured here: 1.2 ms of a 6 ms round trip). Raising
    the mmap and trim thresholds, as real-time guides advise, makes the blocks reused. Once per
    process; ``False`` where the C library is not glibc.
    """
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, 64 << 20)) and bool(mallopt(_M_TRIM_THRESHOLD, 256 << 20))


def open_session(config: ZenohConfig) -> Any:
    """An open Zenoh session (and, once per process, :func:`keep_message_memory`).

    Raises:
        ROSConfigError: Zenoh refused the settings, or cannot listen on an endpoint (in use, not local).
        ROSRuntimeError: The session could not be opened for another reason.
    """
    settings = zenoh_config(config)
    keep_message_memory()
    try:
        return zenoh.open(settings)
    except Exception as exc:
        text = str(exc)
        if config.listen and ("listen" in text.lower() or "bind" in text.lower() or "address" in text.lower()):
            raise ROSConfigError(
                f"cannot listen on {config.listen}: {text}", field="listen", hint="pick a free port or a local address"
            ) from exc
        raise ROSRuntimeError(f"cannot open a Zenoh session ({config.mode}, connect {config.connect}): {text}") from exc
