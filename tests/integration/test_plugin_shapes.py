"""Every built-in plugin can be called the way its group's Protocol says the factories call it.

The registries are typed by these Protocols, so mypy checks each call a factory makes; it cannot
check what an entry point loads. Here each built-in of each group is loaded and its constructor
bound to the arguments the Protocol names: a plugin that drops or renames one fails here, not
at a deployment's start.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import Any

import pytest

from openral_core.errors import ROSDependencyMissing
from openral_core.plugins import (
    DETECTORS_GROUP,
    HALS_GROUP,
    SAFETY_CLIENTS_GROUP,
    SENSOR_BACKENDS_GROUP,
    SIM_ENVS_GROUP,
    SKILLS_GROUP,
)
from openral_hal.protocol import HALPlugin
from openral_perception.detectors.base import DetectorClass
from openral_rskill.base import RSkillPlugin
from openral_runner.safety import SafetyClientPlugin
from openral_runner.sensor_reader import SensorBackendPlugin
from openral_sim.env import SimEnvPlugin

SHAPES: dict[str, tuple[type[Any], str]] = {
    HALS_GROUP: (HALPlugin, "__call__"),
    SENSOR_BACKENDS_GROUP: (SensorBackendPlugin, "from_config"),
    SAFETY_CLIENTS_GROUP: (SafetyClientPlugin, "from_config"),
    SIM_ENVS_GROUP: (SimEnvPlugin, "from_scene"),
    SKILLS_GROUP: (RSkillPlugin, "from_config"),
    DETECTORS_GROUP: (DetectorClass, "from_config"),
}

BUILT_INS = [
    (group, entry.name, entry.value)
    for group in SHAPES
    for entry in entry_points(group=group)
    if entry.value.startswith("openral_")
]


def _arguments(protocol: type[Any], method: str) -> tuple[list[str], dict[str, str]]:
    """The positional and keyword arguments a call through ``protocol.method`` passes (named, not valued)."""
    parameters = list(inspect.signature(getattr(protocol, method)).parameters.values())[1:]  # not self
    positional = [p.name for p in parameters if p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD]
    keywords = {p.name: p.name for p in parameters if p.kind is inspect.Parameter.KEYWORD_ONLY}
    return positional, keywords


def _constructor(plugin: Any, method: str) -> Callable[..., Any]:
    return plugin if method == "__call__" else getattr(plugin, method)  # type: ignore[no-any-return]


@pytest.mark.parametrize(("group", "name", "value"), BUILT_INS, ids=[f"{g}:{n}" for g, n, _ in BUILT_INS])
def test_a_built_in_takes_the_arguments_its_group_passes(group: str, name: str, value: str) -> None:
    entry = next(e for e in entry_points(group=group) if e.name == name)
    try:
        plugin = entry.load()
    except ROSDependencyMissing as exc:
        pytest.skip(f"{value}: {exc}")
    protocol, method = SHAPES[group]
    positional, keywords = _arguments(protocol, method)
    signature = inspect.signature(_constructor(plugin, method))
    try:
        signature.bind(*positional, **keywords)
    except TypeError as exc:
        pytest.fail(f"{group} '{name}' ({value}) cannot be called as {protocol.__name__}.{method}: {exc}")


def test_every_group_the_factories_build_from_has_built_ins() -> None:
    assert {group for group, _, _ in BUILT_INS} == set(SHAPES)


def test_a_plugin_that_drops_a_keyword_is_caught() -> None:
    class Camera:
        @classmethod
        def from_config(cls, config: Any, *, hal: Any, robot: Any) -> Camera:  # no base_dir
            return cls()

    positional, keywords = _arguments(SensorBackendPlugin, "from_config")
    with pytest.raises(TypeError, match="base_dir"):
        inspect.signature(Camera.from_config).bind(*positional, **keywords)
