"""Robot manifests: found through the ``openral.robots`` entry-point group, the shipped ones included.

An entry point names a robot id and points at its manifest: a path (``str``, ``os.PathLike`` or an
``importlib.resources`` ``Traversable``) to a ``robot.yaml``, or a ready ``RobotManifest``. The
shipped manifests are package data (``openral_hal/robots/<robot_id>/robot.yaml``) registered in
``pyproject.toml`` exactly like another package's, so a third party adds a robot without touching
openral. Every file goes through the same bounded, strict reader as a deployment.
"""

from __future__ import annotations

import functools
import os
from importlib.resources import files
from importlib.resources.abc import Traversable

from openral_core.config import validate_model
from openral_core.config_files import parse_config_text, read_config_file
from openral_core.errors import ROSConfigError
from openral_core.plugins import ROBOTS_GROUP, PluginRegistry
from openral_core.robot import RobotManifest

MANIFEST_FILE = "robot.yaml"

RobotManifestSource = RobotManifest | str | os.PathLike[str] | Traversable
"""What an ``openral.robots`` entry point gives: a ready manifest, or where its ``robot.yaml`` is."""

ROBOT_REGISTRY: PluginRegistry[RobotManifestSource] = PluginRegistry(ROBOTS_GROUP, kind="robot", field="hal.robot_id")
"""Robot id → its manifest (a path to ``robot.yaml`` or a ``RobotManifest``)."""


def _shipped(robot_id: str) -> Traversable:
    return files("openral_hal").joinpath("robots", robot_id, MANIFEST_FILE)


SO100_FOLLOWER = _shipped("so100_follower")
SO101_FOLLOWER = _shipped("so101_follower")
ALOHA_BIMANUAL_VIPERX = _shipped("aloha_bimanual_viperx")
BI_SO101_FOLLOWER = _shipped("bi_so101_follower")


def known_robots() -> list[str]:
    """Ids of every registered robot, sorted."""
    return list(ROBOT_REGISTRY)


def load_robot_manifest(robot_id: str) -> RobotManifest:
    """The manifest of ``robot_id``, validated. Cached: every caller shares one frozen object.

    Raises:
        ROSConfigError: ``robot_id`` is not registered (the message lists the known ids and
            suggests the closest, field ``hal.robot_id``), or its manifest is invalid.
    """
    return _load(robot_id)


@functools.cache
def _load(robot_id: str) -> RobotManifest:
    entry = ROBOT_REGISTRY.resolve(robot_id)
    manifest = _manifest_from(entry, robot_id)
    if manifest.robot_id != robot_id:
        raise ROSConfigError(
            f"the manifest registered as robot '{robot_id}' declares robot_id '{manifest.robot_id}'",
            field="robot_id",
            hint="make the robot_id match the name it is registered under",
        )
    return manifest


def _manifest_from(entry: RobotManifestSource, robot_id: str) -> RobotManifest:
    if isinstance(entry, RobotManifest):
        return entry
    if isinstance(entry, Traversable) and not isinstance(entry, os.PathLike):
        source = f"robot '{robot_id}' ({entry})"
        data = parse_config_text(entry.read_text(encoding="utf-8"), source=source)
    elif isinstance(entry, str | os.PathLike):
        path = os.fspath(entry)
        source = f"robot '{robot_id}' ({path})"
        data = parse_config_text(read_config_file(path, field="hal.robot_id"), source=source)
    else:
        raise ROSConfigError(
            f"the openral.robots entry point '{robot_id}' gives a {type(entry).__name__}, "
            "not a RobotManifest or a path to a robot.yaml",
            field="hal.robot_id",
        )
    return validate_model(RobotManifest, data, source=source)
