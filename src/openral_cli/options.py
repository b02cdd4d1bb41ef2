"""Option values that need more than click's types: JSON objects given on the command line."""

from __future__ import annotations

import json
from typing import Any

from openral_core import ROSConfigError


def json_object(text: str | None, option: str) -> dict[str, Any]:
    """The JSON object in ``text`` (empty when not given).

    Raises:
        ROSConfigError: Not JSON, or not an object; naming ``option``.
    """
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ROSConfigError(f"not valid JSON ({exc.msg} at column {exc.colno})", field=option) from None
    if not isinstance(value, dict):
        raise ROSConfigError("must be a JSON object, e.g. '{\"gain\": 2}'", field=option)
    return value
