"""The one table of names: everything the spec names is there, each name means one thing."""

from __future__ import annotations

from openral_observability import semconv

NAMED_BY_SPEC = {
    # spans
    "rskill.tick",
    "sensors.read_latest",
    "world_state.snapshot",
    "rskill.execute",
    "skill.chunk_inference",
    "safety.check",
    "hal.read_state",
    "hal.send_action",
    "cli.command",
    # metrics
    "openral.tick.duration",
    "openral.inference.duration",
    "openral.hal.read_state.duration",
    "openral.hal.send_action.duration",
    "openral.sensors.age_ms",
    "openral.world_state.staleness_ms",
    "openral.world_state.components_stale",
    "openral.tick.deadline_misses",
    "openral.tick.budget_violations",
    "openral.safety.violations",
    "openral.sensors.stale_reads",
    # events
    "openral.event.deadline_missed",
    "openral.event.sensor_stale",
    "openral.event.staleness_latched",
    "openral.event.error_latched",
    "openral.event.safety_violation",
    "openral.event.action_dropped",
    "openral.event.estop_requested",
}


def _table(prefix: str) -> dict[str, str]:
    return {name: value for name, value in vars(semconv).items() if name.startswith(prefix) and isinstance(value, str)}


def test_every_name_the_spec_uses_is_in_the_table() -> None:
    values = {value for value in vars(semconv).values() if isinstance(value, str)}
    assert sorted(NAMED_BY_SPEC - values) == []


def test_names_are_unique_within_each_kind() -> None:
    for prefix in ("SPAN_", "METRIC_", "EVENT_", "ATTR_"):
        table = _table(prefix)
        assert len(set(table.values())) == len(table), prefix


def test_layered_names_follow_the_openral_namespace() -> None:
    assert all(v.startswith("openral.") for v in _table("METRIC_").values())
    assert all(v.startswith("openral.event.") for v in _table("EVENT_").values())
    hal = [v for v in _table("METRIC_").values() if v.startswith("openral.hal.")]
    assert hal
    assert all(v.endswith(".duration") for v in hal)
