"""PluginRegistry: names without imports, lazy cached loading, helpful unknown-name errors."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from openral_core import ROSConfigError
from openral_core import plugins as plugins_module
from openral_core.plugins import HALS_GROUP, SAFETY_CLIENTS_GROUP, SKILLS_GROUP, PluginRegistry


@dataclass
class FakeEntryPoint:
    name: str
    value: object
    loads: list[str] = field(default_factory=list)

    def load(self) -> object:
        self.loads.append(self.name)
        return self.value


class Alpha:
    pass


class Beta:
    pass


@pytest.fixture
def fake_group(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, FakeEntryPoint]]:
    entries = {
        "zeta_cam": FakeEntryPoint("zeta_cam", Beta),
        "gstreamer": FakeEntryPoint("gstreamer", Alpha),
        "opencv_thread": FakeEntryPoint("opencv_thread", Beta),
    }
    calls: list[str] = []

    def fake_entry_points(*, group: str) -> list[FakeEntryPoint]:
        calls.append(group)
        return list(entries.values()) if group == "test.group" else []

    monkeypatch.setattr(plugins_module, "entry_points", fake_entry_points)
    yield entries
    assert calls == ["test.group"], "entry points must be read once, at construction"


def _registry() -> PluginRegistry:
    return PluginRegistry("test.group", kind="sensor backend", field="sensors[0].backend")


def test_names_are_listed_sorted_without_loading(fake_group: dict[str, FakeEntryPoint]) -> None:
    registry = _registry()
    assert list(registry) == ["gstreamer", "opencv_thread", "zeta_cam"]
    assert len(registry) == 3
    assert "gstreamer" in registry
    assert "v4l2" not in registry
    assert 3 not in registry
    assert all(not ep.loads for ep in fake_group.values()), "listing must not import any plugin"


def test_lookup_loads_once_and_caches(fake_group: dict[str, FakeEntryPoint]) -> None:
    registry = _registry()
    assert registry["gstreamer"] is Alpha
    assert registry["gstreamer"] is Alpha
    assert fake_group["gstreamer"].loads == ["gstreamer"]
    assert fake_group["opencv_thread"].loads == [], "only the selected plugin is imported"


def test_unknown_name_lists_known_and_suggests_closest(fake_group: dict[str, FakeEntryPoint]) -> None:
    registry = _registry()
    with pytest.raises(ROSConfigError) as info:
        registry["gstremer"]
    error = info.value
    assert error.field == "sensors[0].backend"
    assert error.hint == "did you mean 'gstreamer'?"
    assert str(error) == (
        "sensors[0].backend: unknown sensor backend 'gstremer'; known: gstreamer, opencv_thread, zeta_cam "
        "(did you mean 'gstreamer'?)"
    )


def test_unknown_name_without_a_close_match_says_what_to_install(fake_group: dict[str, FakeEntryPoint]) -> None:
    with pytest.raises(ROSConfigError, match="install the plugin that provides 'holoscan'"):
        _registry()["holoscan"]


def test_get_returns_the_default_for_an_unknown_name(fake_group: dict[str, FakeEntryPoint]) -> None:
    registry = _registry()
    assert registry.get("gstreamer") is Alpha
    try:
        missing = registry.get("v4l2", "fallback")
    except ROSConfigError:
        pytest.fail(
            "PluginRegistry.get() raises for an unknown name: Mapping.get only catches KeyError and __getitem__ "
            "raises ROSConfigError; override get() (or make the unknown-name error also a KeyError)"
        )
    assert missing == "fallback"


def test_empty_group_says_none_are_known(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(plugins_module, "entry_points", lambda *, group: [])
    registry = PluginRegistry("empty.group", kind="HAL adapter", field="hal.adapter")
    assert list(registry) == []
    with pytest.raises(ROSConfigError, match="unknown HAL adapter 'so101'; known: none"):
        registry["so101"]


@pytest.mark.parametrize(
    ("group", "names"),
    [
        (SKILLS_GROUP, {"hello", "noop"}),
        (HALS_GROUP, {"mujoco_twin", "null"}),
        (SAFETY_CLIENTS_GROUP, {"envelope", "null"}),
    ],
)
def test_built_ins_are_registered_like_plugins(group: str, names: set[str]) -> None:
    registry = PluginRegistry(group, kind="plugin", field="x")
    assert names <= set(registry), f"{group} lacks built-ins: {names - set(registry)}"
    assert list(registry) == sorted(registry)


def test_real_group_unknown_name() -> None:
    registry = PluginRegistry(SKILLS_GROUP, kind="skill", field="vla.id")
    with pytest.raises(ROSConfigError, match=r"vla\.id: unknown skill 'helo'; known: .*hello.*did you mean 'hello'"):
        registry["helo"]


def test_resolve_names_the_field_that_selected_the_plugin(fake_group: dict[str, FakeEntryPoint]) -> None:
    registry = _registry()
    assert registry.resolve("gstreamer", field="sensors[2].backend") is Alpha
    with pytest.raises(ROSConfigError) as info:
        registry.resolve("gstremer", field="sensors[2].backend")
    assert info.value.field == "sensors[2].backend"
    assert info.value.hint == "did you mean 'gstreamer'?"
    with pytest.raises(ROSConfigError) as default:
        registry.resolve("gstremer")
    assert default.value.field == "sensors[0].backend"
