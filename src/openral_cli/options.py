"""Option values that need more than click's types: seconds, and JSON objects given on the command line."""

from __future__ import annotations

import json
import math
from typing import Any

import click

from openral_core import ROSConfigError


class Seconds(click.ParamType):  # type: ignore[type-arg]
    """A finite number of seconds (``nan`` and ``inf`` are refused): every seconds-valued option takes this type.

    Args:
        minimum: The least value taken: ``0`` takes any positive number (zero only with ``zero_ok``).
        zero_ok: ``0`` is taken too (a pause that can be skipped).
        maximum: The most taken (``None``: no limit).
    """

    name = "seconds"

    def __init__(self, minimum: float = 0.0, *, zero_ok: bool = False, maximum: float | None = None) -> None:
        self.minimum = minimum
        self.zero_ok = zero_ok
        self.maximum = maximum

    def convert(self, value: object, param: click.Parameter | None, ctx: click.Context | None) -> float:
        try:
            seconds = float(value)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number of seconds", param, ctx)
        if not math.isfinite(seconds):
            self.fail(f"{value!r} must be a finite number of seconds", param, ctx)
        if self.zero_ok and seconds == 0:
            return seconds
        if self.minimum > 0 and seconds < self.minimum:
            self.fail(f"{value!r} must be at least {self.minimum:g} s", param, ctx)
        if seconds <= 0:
            self.fail(
                f"{value!r} must be a {'non-negative' if self.zero_ok else 'positive'} number of seconds", param, ctx
            )
        if self.maximum is not None and seconds > self.maximum:
            self.fail(f"{value!r} must be at most {self.maximum:g} s", param, ctx)
        return seconds


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
