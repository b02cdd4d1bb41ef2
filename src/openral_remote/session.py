"""Opening a Zenoh session from a :class:`~openral_remote.config.ZenohConfig`, errors translated."""

from __future__ import annotations

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


def open_session(config: ZenohConfig) -> Any:
    """An open Zenoh session.

    Raises:
        ROSConfigError: Zenoh refused the settings, or cannot listen on an endpoint (in use, not local).
        ROSRuntimeError: The session could not be opened for another reason.
    """
    settings = zenoh_config(config)
    try:
        return zenoh.open(settings)
    except Exception as exc:
        text = str(exc)
        if config.listen and ("listen" in text.lower() or "bind" in text.lower() or "address" in text.lower()):
            raise ROSConfigError(
                f"cannot listen on {config.listen}: {text}", field="listen", hint="pick a free port or a local address"
            ) from exc
        raise ROSRuntimeError(f"cannot open a Zenoh session ({config.mode}, connect {config.connect}): {text}") from exc
