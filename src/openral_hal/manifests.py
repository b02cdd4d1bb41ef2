"""Robot manifests shipped with openral: ``openral_hal/robots/<robot_id>/robot.yaml``.

They are package data read through ``importlib.resources``, so they are found the same way
from a source checkout, an installed wheel or a zip import.
"""

from __future__ import annotations

import difflib
import functools
from importlib.resources import files
from importlib.resources.abc import Traversable

from openral_core.config import validate_model
from openral_core.config_files import parse_config_text
from openral_core.errors import ROSConfigError
from openral_core.robot import RobotManifest

MANIFEST_FILE = "robot.yaml"


def _robots_dir() -> Traversable:
    return files("openral_hal").joinpath("robots")


def known_robots() -> list[str]:
    """Ids of every shipped robot manifest, sorted."""
    return list(_known())


@functools.cache
def _known() -> tuple[str, ...]:
    return tuple(
        sorted(
            entry.name
            for entry in _robots_dir().iterdir()
            if entry.is_dir() and entry.joinpath(MANIFEST_FILE).is_file()
        )
    )


def load_robot_manifest(robot_id: str) -> RobotManifest:
    """The manifest of ``robot_id``, validated. Cached: every caller shares one frozen object.

    Raises:
        ROSConfigError: ``robot_id`` is not a shipped robot (the message lists the known ids and
            suggests the closest, field ``hal.robot_id``), or its manifest is invalid.
    """
    known = _known()
    if robot_id not in known:
        close = difflib.get_close_matches(robot_id, known, n=1)
        raise ROSConfigError(
            f"unknown robot '{robot_id}'; known robots: {', '.join(known) or 'none'}",
            field="hal.robot_id",
            hint=f"did you mean '{close[0]}'?" if close else None,
        )
    return _load(robot_id)


@functools.cache
def _load(robot_id: str) -> RobotManifest:
    resource = _robots_dir().joinpath(robot_id, MANIFEST_FILE)
    source = f"openral_hal/robots/{robot_id}/{MANIFEST_FILE}"
    data = parse_config_text(resource.read_text(encoding="utf-8"), source=source)
    manifest = validate_model(RobotManifest, data, source=source)
    if manifest.robot_id != robot_id:
        raise ROSConfigError(
            f"{source} declares robot_id '{manifest.robot_id}' but lives in the directory '{robot_id}'",
            field="robot_id",
            hint="make the robot_id match its directory name",
        )
    return manifest
