"""Turning YAML and pydantic errors into one clear ``ROSConfigError``."""

from __future__ import annotations

import difflib
import json
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from openral_core.config_files import CONFIG_DIR, is_plain, load_config_file
from openral_core.errors import ROSConfigError

ModelT = TypeVar("ModelT", bound=BaseModel)


def load_model_yaml(model: type[ModelT], path: Path, *, field: str | None = None) -> ModelT:
    """Read ``path`` (YAML, or JSON for ``.json``) and validate it as ``model``.

    Args:
        field: The option or field that named the file (``--config``, ``vla.manifest``); file-level
            errors name it, and field errors inside the file say which file they are in.

    Raises:
        ROSConfigError: Unreadable or hostile file, invalid YAML, or a field error (named, with a fix).
    """
    data = load_config_file(path, field=field)
    if not isinstance(data, dict):
        kind = "nothing" if data is None else type(data).__name__
        raise ROSConfigError(f"{path} must hold a mapping at the top level, not {kind}", field=field)
    source = f"{field}: {path}" if field else str(path)
    return validate_model(model, data, source=source, context={CONFIG_DIR: str(path.resolve().parent)})


def validate_model(
    model: type[ModelT],
    data: Any,
    *,
    source: str | None = None,
    field_prefix: str | None = None,
    context: dict[str, Any] | None = None,
) -> ModelT:
    """Validate ``data`` as ``model``, raising ``ROSConfigError`` that names the first bad field.

    Plain data (what a configuration file holds) is validated strictly, as JSON: a boolean is not
    a number and text is not a number (``rate_hz: true`` or ``rate_hz: "30"`` is an error, not 1 Hz
    or a silent conversion). Python objects from code are validated in pydantic's usual lax mode.

    Args:
        source: Where the data came from (a file, a plugin), appended to the message.
        field_prefix: Dotted path of ``data`` in the deployment (``hal.params``), prepended to field names.
        context: Pydantic's validation context; files read by :func:`load_model_yaml` put their
            folder under ``CONFIG_DIR`` (a model that resolves relative paths takes it from there).
    """
    try:
        if is_plain(data):
            return model.model_validate_json(json.dumps(data), strict=True, context=context)
        return model.model_validate(data, context=context)
    except ValidationError as exc:
        raise config_error_from_validation(exc, model, source=source, field_prefix=field_prefix) from exc


def config_error_from_validation(
    exc: ValidationError, model: type[BaseModel], *, source: str | None = None, field_prefix: str | None = None
) -> ROSConfigError:
    """Describe a pydantic ``ValidationError`` as a single ``ROSConfigError``."""
    errors = exc.errors(include_url=False)
    first = errors[0]
    field = _dotted(first["loc"])
    if field_prefix:
        field = f"{field_prefix}{'' if field.startswith('[') else '.'}{field}" if field else field_prefix
    message, hint = _describe(first, model)
    if len(errors) > 1:
        others = ", ".join(_dotted(e["loc"]) or "<root>" for e in errors[1:4])
        message = f"{message}; also invalid: {others}"
    if source:
        message = f"{message} [in {source}]"
    return ROSConfigError(message, field=field or None, hint=hint)


def _dotted(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


def _describe(error: Any, model: type[BaseModel]) -> tuple[str, str | None]:
    kind = error["type"]
    loc = error["loc"]
    if kind == "extra_forbidden":
        allowed = _allowed_keys(model, loc[:-1])
        key = str(loc[-1])
        close = difflib.get_close_matches(key, allowed, n=1)
        hint = f"did you mean '{close[0]}'?" if close else None
        return f"unknown key '{key}'; allowed keys: {', '.join(sorted(allowed))}", hint
    if kind == "missing":
        return "is required but missing", "add it to the file"
    message = str(error["msg"])
    if kind in _TYPE_ERRORS:
        message = f"{message}, got {_describe_input(error.get('input'))}"
    if message.startswith("Value error, "):
        message = message[len("Value error, ") :]
    return message, None


_TYPE_ERRORS = frozenset({"float_type", "int_type", "bool_type", "string_type", "list_type", "dict_type", "tuple_type"})


def _describe_input(value: Any) -> str:
    if isinstance(value, bool):
        return f"a boolean ({str(value).lower()}): booleans are not numbers"
    if isinstance(value, str):
        shown = value if len(value) <= 40 else value[:37] + "..."
        return f"text {shown!r}"
    if value is None:
        return "null"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    return f"{type(value).__name__} {value!r}"[:60]


def _allowed_keys(model: type[BaseModel], loc: tuple[int | str, ...]) -> list[str]:
    current: Any = model
    for part in loc:
        if isinstance(part, int):
            continue
        if not (isinstance(current, type) and issubclass(current, BaseModel)):
            return []
        info = current.model_fields.get(str(part))
        if info is None:
            return []
        current = _model_in(info.annotation)
    if isinstance(current, type) and issubclass(current, BaseModel):
        return list(current.model_fields)
    return []


def _model_in(annotation: Any) -> Any:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()) or ():
        found = _model_in(arg)
        if found is not None:
            return found
    return None
