"""A LeRobot device's config (robot, teleoperator or camera) built from a deployment's ``type`` and params.

LeRobot registers each device type with ``draccus.ChoiceRegistry`` when the module that defines
it is imported, and decodes a config with draccus. openral does the same: it imports LeRobot's
own device packages of that kind (and the installed third-party plugins) and decodes the params
with LeRobot's own config class, so every key, default and check is LeRobot's. Errors name the
deployment's field (``hal.params.port``) and, for an unknown type, the known ones.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import importlib
import pkgutil
import sys
from collections.abc import Mapping
from typing import Any, Literal

from openral_core.errors import ROSConfigError, ROSDependencyMissing
from openral_hal.lerobot.plugins import load_lerobot_plugins

DeviceKind = Literal["robot", "teleoperator", "camera"]

_PACKAGES: dict[DeviceKind, tuple[str, str, str]] = {
    "robot": ("lerobot.robots", "lerobot.robots.config", "RobotConfig"),
    "teleoperator": ("lerobot.teleoperators", "lerobot.teleoperators.config", "TeleoperatorConfig"),
    "camera": ("lerobot.cameras", "lerobot.cameras.configs", "CameraConfig"),
}
_NOT_DEVICES = frozenset({"config", "configs", "utils", "robot", "teleoperator", "camera"})


def require_lerobot(needed_for: str) -> None:
    """Raise a clear error when the ``lerobot`` extra is not installed.

    Raises:
        ROSDependencyMissing: ``lerobot`` cannot be imported.
    """
    try:
        importlib.import_module("lerobot")
    except ImportError as exc:
        raise ROSDependencyMissing(
            exc.name or "lerobot",
            extra="lerobot",
            needed_for=needed_for,
            install=None
            if sys.version_info >= (3, 12)
            else f"lerobot 0.6 needs Python 3.12 or newer, and this is {sys.version.split()[0]}: "
            "uv sync --python 3.12 --extra lerobot",
        ) from exc


@functools.cache
def _device_base(kind: DeviceKind) -> tuple[Any, tuple[str, ...]]:
    """The kind's config base class, after importing LeRobot's own device modules; the ones that failed."""
    package_name, module_name, class_name = _PACKAGES[kind]
    package = importlib.import_module(package_name)
    failed = []
    for module in pkgutil.iter_modules(package.__path__):
        if module.ispkg and module.name not in _NOT_DEVICES:
            try:
                importlib.import_module(f"{package_name}.{module.name}")
            except Exception as exc:  # a device whose SDK is not installed: named if asked for
                failed.append(f"{module.name} ({type(exc).__name__}: {exc})")
    return getattr(importlib.import_module(module_name), class_name), tuple(failed)


def known_types(kind: DeviceKind) -> list[str]:
    """Every registered type of this kind, LeRobot's and the installed plugins', sorted."""
    require_lerobot(f"LeRobot {kind}s")
    base, _ = _device_base(kind)
    load_lerobot_plugins()
    return sorted(base.get_known_choices())


def device_config_class(kind: DeviceKind, type_name: str, *, field: str) -> Any:
    """LeRobot's config class registered as ``type_name``.

    Raises:
        ROSConfigError: No such type (the message lists the known ones, the closest first, and the
            device packages that could not be imported).
    """
    require_lerobot(f"LeRobot {kind}s")
    base, failed = _device_base(kind)
    load_lerobot_plugins()
    choices = sorted(base.get_known_choices())
    if type_name in choices:
        return base.get_choice_class(type_name)
    close = difflib.get_close_matches(type_name, choices, n=1)
    hint = f"did you mean '{close[0]}'? " if close else ""
    hint += f"known: {', '.join(choices)}"
    if failed:
        hint += f"; not importable here: {'; '.join(failed)}"
    raise ROSConfigError(f"LeRobot has no {kind} type '{type_name}'", field=f"{field}.type", hint=hint)


def build_device_config(kind: DeviceKind, type_name: str, params: Mapping[str, Any], *, field: str) -> Any:
    """Decode ``params`` with the LeRobot config class of ``type_name`` (its keys, defaults and checks).

    Args:
        field: Where the params are in the deployment (``hal.params``), for errors.

    Raises:
        ROSConfigError: An unknown type, an unknown or missing key, or a value LeRobot refuses.
    """
    require_lerobot(f"LeRobot {kind}s")
    import draccus  # noqa: PLC0415  (the extra)

    config_class = device_config_class(kind, type_name, field=field)
    if kind != "camera":
        _device_base("camera")  # a robot's or teleoperator's cameras are decoded with it
    try:
        return draccus.decode(config_class, dict(params))
    except draccus.utils.DecodingError as exc:
        path, message = _decoding_error(exc)
        allowed = sorted(f.name for f in dataclasses.fields(config_class) if f.init)
        where = ".".join((field, *path)) if path else field
        if message.startswith(("The fields", "Missing required field")) and "`" in message:
            named = message.split("`")[1].split(",")[0].strip()
            where = ".".join((field, *path, named))
        hint = None if path else f"allowed keys: {', '.join(allowed)}"
        raise ROSConfigError(f"{message} (LeRobot {kind} '{type_name}')", field=where, hint=hint) from exc
    except draccus.utils.ParsingError as exc:  # a value LeRobot's own checks (__post_init__) refuse
        reason = " ".join(str(exc.__cause__ or exc).split())
        raise ROSConfigError(f"LeRobot refuses this {kind} config: {reason}", field=field) from exc
    except (TypeError, ValueError) as exc:
        raise ROSConfigError(f"LeRobot refuses this {kind} config: {exc}", field=field) from exc


def _decoding_error(exc: Exception) -> tuple[tuple[str, ...], str]:
    args = exc.args
    if len(args) == 2 and isinstance(args[0], tuple):
        return tuple(str(part) for part in args[0]), str(args[1]).strip()
    return (), str(exc).strip()


def make_device(kind: Literal["robot", "teleoperator"], config: Any, *, field: str) -> Any:
    """LeRobot's robot or teleoperator for ``config``, by LeRobot's own factory; no port is opened.

    Raises:
        ROSConfigError: LeRobot cannot build it here (a missing SDK is named) or refuses the config.
    """
    if kind == "robot":
        from lerobot.robots.utils import make_robot_from_config as make  # noqa: PLC0415  (the extra)
    else:
        from lerobot.teleoperators.utils import make_teleoperator_from_config as make  # noqa: PLC0415

    try:
        return make(config)
    except ImportError as exc:
        raise ROSConfigError(
            f"LeRobot's '{config.type}' {kind} cannot be built here: {exc}",
            field=f"{field}.type",
            hint=f"install the package that provides '{exc.name}'" if exc.name else None,
        ) from exc
    except Exception as exc:  # LeRobot's constructors refuse with any exception type
        raise ROSConfigError(f"LeRobot refuses to build the '{config.type}' {kind}: {exc}", field=field) from exc
