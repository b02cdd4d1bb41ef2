"""``DETECTOR_REGISTRY``: the detector kinds installed, a read-only view over the ``openral.detectors`` group.

Built-ins (``motion``, ``scene_change``, ``objects``) are registered in ``pyproject.toml`` exactly
as a third party registers its own; a kind's module is imported only when a deployment names it.
"""

from __future__ import annotations

from pathlib import Path

from openral_core import ROSConfigError
from openral_core.plugins import DETECTORS_GROUP, PluginRegistry
from openral_perception.detectors.base import DetectorClass, EventDetector
from openral_perception.params import DetectorEntry

DETECTOR_REGISTRY: PluginRegistry[DetectorClass] = PluginRegistry(
    DETECTORS_GROUP, kind="detector", field="detectors[].kind"
)
"""``kind -> detector class``; an unknown kind is a ``ROSConfigError`` listing the known ones."""


def build_detector(entry: DetectorEntry, *, base_dir: Path | None = None, field: str | None = None) -> EventDetector:
    """The detector ``entry`` configures, built by its class's ``from_config``.

    Args:
        entry: The detector's kind and params, and where they sit in the file.
        base_dir: Folder a relative file path is resolved against (the deployment file's).
        field: Where the perception params sit (``observers[].params``); errors name fields below it.

    Raises:
        ROSConfigError: An unknown kind (listing the known ones) or a wrong parameter, named as
            ``<field>.<params_field>.<key>``.
    """
    prefix = f"{field}." if field else ""
    cls = DETECTOR_REGISTRY.resolve(entry.config.kind, field=prefix + entry.kind_field)
    try:
        return cls.from_config(entry.config.params, base_dir=base_dir)
    except ROSConfigError as exc:
        if type(exc) is not ROSConfigError:  # a missing dependency or a licence says what it is as it is
            raise
        raise _below(exc, prefix + entry.params_field) from exc


def _below(error: ROSConfigError, field: str) -> ROSConfigError:
    """The same error with its field taken as relative to ``field``."""
    message = str(error)
    if error.field:
        message = message.removeprefix(f"{error.field}: ")
    if error.hint:
        message = message.removesuffix(f" ({error.hint})")
    return ROSConfigError(message, field=f"{field}.{error.field}" if error.field else field, hint=error.hint)
