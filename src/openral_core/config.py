"""Turning YAML and pydantic errors into one clear ``ROSConfigError``."""

from __future__ import annotations

import copy
import difflib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from openral_core.config_files import CONFIG_DIR, is_plain, load_config_file, parse_config_text
from openral_core.errors import ROSConfigError

ModelT = TypeVar("ModelT", bound=BaseModel)


def load_model_yaml(
    model: type[ModelT], path: Path, *, field: str | None = None, overrides: Sequence[str] = ()
) -> ModelT:
    """Read ``path`` (YAML, or JSON for ``.json``) and validate it as ``model``.

    Args:
        field: The option or field that named the file (``--config``, ``vla.manifest``); file-level
            errors name it, and field errors inside the file say which file they are in.
        overrides: ``dotted.key=value`` assignments applied to the file's data before validation
            (:func:`apply_overrides`), so an override is checked exactly as the file's own value is.

    Raises:
        ROSConfigError: Unreadable or hostile file, invalid YAML, a malformed override, or a field
            error (named, with a fix).
    """
    data = load_config_file(path, field=field)
    if not isinstance(data, dict):
        kind = "nothing" if data is None else type(data).__name__
        raise ROSConfigError(f"{path} must hold a mapping at the top level, not {kind}", field=field)
    data = apply_overrides(data, overrides)
    source = f"{field}: {path}" if field else str(path)
    return validate_model(model, data, source=source, context={CONFIG_DIR: str(path.resolve().parent)})


def apply_overrides(data: dict[str, Any], assignments: Sequence[str], *, option: str = "--set") -> dict[str, Any]:
    """``data`` with each ``dotted.key=value`` assignment set (the value read as YAML: ``2``, ``null``, ``{ticks: 3}``).

    Intermediate mappings are created where missing; a key below a value that is not a mapping is
    refused rather than replacing it. ``data`` itself is not changed.

    Raises:
        ROSConfigError: An assignment without ``=``, with an empty key part, or with a value that is not YAML.
    """
    result = copy.deepcopy(data)
    for assignment in assignments:
        key, equals, text = assignment.partition("=")
        parts = key.strip().split(".")
        if not equals or not all(parts):
            raise ROSConfigError(
                f"{option} {assignment!r} is not KEY=VALUE", field=option, hint="e.g. --set virtual_latency.ticks=2"
            )
        # Read as a file's value is: bounded, no duplicate keys, plain data only.
        value = parse_config_text(text, source=f"{option} {assignment!r}", field=option)
        target = result
        for depth, part in enumerate(parts[:-1]):
            child = target.get(part)
            if child is None:  # absent, or null in the file: the assignment gives it its keys
                child = target[part] = {}
            if not isinstance(child, dict):
                above = ".".join(parts[: depth + 1])
                raise ROSConfigError(
                    f"{option} {assignment!r}: {above} is {child!r}, not a mapping with keys", field=option
                )
            target = child
        target[parts[-1]] = value
    return result


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
    errors: list[dict[str, Any]] = [
        {**error, "loc": _field_path(model, error["loc"])} for error in exc.errors(include_url=False)
    ]
    first = errors[0]
    field = _dotted(first["loc"])
    if field_prefix:
        field = f"{field_prefix}{'' if field.startswith('[') else '.'}{field}" if field else field_prefix
    message, hint = _describe(first, model)
    # A field of several accepted forms fails once per form: the forms failed at the same place are
    # told together, and one whose error lies deeper (inside the first form) is not repeated.
    forms = [e for e in errors[1:] if e["loc"] == first["loc"]]
    if forms:
        message = " or ".join(dict.fromkeys([message, *(_describe(e, model)[0] for e in forms)]))
    others = [e for e in errors[1:] if first["loc"][: len(e["loc"])] != e["loc"]]
    if others:
        message = f"{message}; also invalid: {', '.join(_dotted(e['loc']) or '<root>' for e in others[:3])}"
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


def _field_path(model: type[BaseModel], loc: tuple[int | str, ...]) -> tuple[int | str, ...]:
    """``loc`` without pydantic's union-member tags (``VirtualLatency``, ``literal['measured']``): field names only.

    A tag follows a field whose annotation is a union: it is the member model's class name, or
    the name pydantic gives a member that is no model.
    """
    path: list[int | str] = []
    current: Any = model
    tagged = False
    for part in loc:
        if isinstance(part, int):
            path.append(part)
            continue
        if isinstance(current, type) and issubclass(current, BaseModel):
            info = current.model_fields.get(part)
            if info is not None:
                path.append(part)
                annotation = info.annotation
                tagged = len(getattr(annotation, "__args__", ()) or ()) > 1
                current = _model_in(annotation)
                continue
        if tagged:
            tagged = False  # the member's tag: the next parts are that member's fields
            continue
        path.append(part)
        current = None
    return tuple(path)


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
