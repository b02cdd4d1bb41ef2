"""``openral serve``'s batching and admission options, one per field of :class:`~openral_remote.admission.ServeLimits`.

The options are generated from the model, so the command line, its help and the server's
defaults cannot drift apart; a value the model refuses names the option.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import click
from pydantic import ValidationError

from openral_core import ROSConfigError
from openral_remote.admission import ServeLimits

_F = TypeVar("_F", bound=Callable[..., Any])


def _option_name(field: str) -> str:
    return "--" + field.replace("_", "-")


def limit_options(command: _F) -> _F:
    """Add ``--max-batch``, ``--max-wait-ms`` and the other limits to ``command`` (each defaults to the model's)."""
    for name, field in reversed(list(ServeLimits.model_fields.items())):
        kind = float if field.annotation is float else int
        command = click.option(
            _option_name(name),
            name,
            type=kind,
            default=field.default,
            show_default=True,
            help=field.description,
        )(command)
    return command


def serve_limits(values: dict[str, Any]) -> ServeLimits:
    """The limits the options give (``values``: the command's keyword arguments; others are ignored).

    Raises:
        ROSConfigError: A value out of range, naming its option.
    """
    chosen = {name: values[name] for name in ServeLimits.model_fields if name in values}
    try:
        return ServeLimits(**chosen)
    except ValidationError as exc:
        error = exc.errors()[0]
        field = str(error["loc"][0]) if error["loc"] else ""
        raise ROSConfigError(str(error["msg"]), field=_option_name(field)) from None


__all__ = ["limit_options", "serve_limits"]
