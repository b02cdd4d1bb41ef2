"""Turning YAML and pydantic errors into one clear ``ROSConfigError``."""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from openral_core.errors import ROSConfigError

ModelT = TypeVar("ModelT", bound=BaseModel)


def load_model_yaml(model: type[ModelT], path: Path) -> ModelT:
    """Read ``path`` as YAML and validate it as ``model``.

    Raises:
        ROSConfigError: Missing file, invalid YAML, or a field error (named, with a fix).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise ROSConfigError(f"file not found: {path}", hint="check the path") from exc
    except OSError as exc:
        raise ROSConfigError(f"cannot read {path}: {exc.strerror}") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ROSConfigError(f"{path} is not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ROSConfigError(f"{path} must hold a mapping at the top level, not {type(data).__name__}")
    return validate_model(model, data, source=str(path))


def validate_model(
    model: type[ModelT], data: Any, *, source: str | None = None, field_prefix: str | None = None
) -> ModelT:
    """Validate ``data`` as ``model``, raising ``ROSConfigError`` that names the first bad field.

    Args:
        source: Where the data came from (a file, a plugin), appended to the message.
        field_prefix: Dotted path of ``data`` in the deployment (``hal.params``), prepended to field names.
    """
    try:
        return model.model_validate(data)
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
        field = f"{field_prefix}.{field}" if field else field_prefix
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
    if message.startswith("Value error, "):
        message = message[len("Value error, ") :]
    return message, None


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
