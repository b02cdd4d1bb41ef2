"""Entry-point plugin registries: how every kind of plugin (skills, HALs, sensors, detectors, ...) is found.

Built-ins are registered in ``pyproject.toml`` exactly like third-party plugins. A registry
lists entry-point names without importing anything; a plugin's module is imported only
when that plugin is resolved, so heavy backends load only when a deployment selects them.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterator, Mapping
from importlib.metadata import EntryPoint, entry_points
from typing import Any, TypeVar

from openral_core.errors import ROSConfigError

SKILLS_GROUP = "openral.skills"
SENSOR_BACKENDS_GROUP = "openral.sensor_backends"
HALS_GROUP = "openral.hals"
SAFETY_CLIENTS_GROUP = "openral.safety_clients"
ROBOTS_GROUP = "openral.robots"
OBSERVERS_GROUP = "openral.observers"
SIM_ENVS_GROUP = "openral.sim_envs"
DETECTORS_GROUP = "openral.detectors"

T = TypeVar("T")


class PluginRegistry(Mapping[str, T]):
    """A read-only ``name -> plugin object`` view over one entry-point group, typed by what the group holds.

    Each group's type is a Protocol beside the seam it builds (``HALPlugin`` beside ``HAL``,
    ``SensorBackendPlugin`` beside ``SensorReader``, ...): the registry does not check a loaded
    object against it, but every call a caller makes through the registry is type-checked.

    Names are read once at construction; each object is loaded on first lookup and cached.
    Looking up an unknown name raises ``ROSConfigError`` listing the known names and the
    closest match.

    Args:
        group: Entry-point group name.
        kind: Human word for the plugins ("skill", "HAL adapter"), used in messages.
        field: Configuration field that selects a plugin, used in messages.
    """

    def __init__(self, group: str, *, kind: str, field: str) -> None:
        self.group = group
        self.kind = kind
        self.field = field
        self._entry_points: dict[str, EntryPoint] = {ep.name: ep for ep in entry_points(group=group)}
        self._loaded: dict[str, T] = {}

    def __getitem__(self, name: str) -> T:
        if name in self._loaded:
            return self._loaded[name]
        entry = self._entry_points.get(name)
        if entry is None:
            raise self.unknown(name)
        obj: T = entry.load()
        self._loaded[name] = obj
        return obj

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(self._entry_points))

    def __len__(self) -> int:
        return len(self._entry_points)

    def get(self, name: str, default: Any = None) -> Any:
        """The plugin, or ``default`` when ``name`` is not registered."""
        return self[name] if name in self._entry_points else default

    def __contains__(self, name: object) -> bool:
        return name in self._entry_points

    def resolve(self, name: str, *, field: str | None = None) -> T:
        """Like ``registry[name]``, but an unknown name's error names ``field`` (e.g. ``sensors[2].backend``)."""
        if name not in self._entry_points:
            raise self.unknown(name, field=field)
        return self[name]

    def unknown(self, name: str, *, field: str | None = None) -> ROSConfigError:
        """The error for a name that is not registered."""
        known = sorted(self._entry_points)
        close = difflib.get_close_matches(name, known, n=1)
        hint = f"did you mean '{close[0]}'?" if close else f"install the plugin that provides '{name}'"
        return ROSConfigError(
            f"unknown {self.kind} '{name}'; known: {', '.join(known) or 'none'}",
            field=field or self.field,
            hint=hint,
        )
