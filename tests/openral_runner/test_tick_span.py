"""Tick span attributes: timings always, outcome fields only when they apply, names from one table."""

from __future__ import annotations

from openral_core import TickResult
from openral_observability import semconv
from openral_runner.tick_span import tick_span_attributes

BASE = {semconv.ATTR_SKILL_ID: "wave"}


def test_an_on_time_tick_carries_its_timings_and_no_outcome_fields() -> None:
    result = TickResult(tick_idx=4, tick_ms=1.5, inference_ms=0.75, action_applied=True)
    attributes = tick_span_attributes(result, BASE)
    assert attributes[semconv.ATTR_SKILL_ID] == "wave"
    assert attributes[semconv.ATTR_TICK_IDX] == 4
    assert attributes[semconv.ATTR_INFERENCE_MS] == 0.75
    assert attributes[semconv.ATTR_ACTION_APPLIED] is True
    for absent in (semconv.ATTR_WITHHELD_REASON, semconv.ATTR_LATENESS_MS, semconv.ATTR_EPISODE_IDX):
        assert absent not in attributes
    assert BASE == {semconv.ATTR_SKILL_ID: "wave"}  # a new dict: the span may keep it


def test_a_late_withheld_episode_tick_says_why_and_where() -> None:
    result = TickResult(
        tick_idx=9,
        withheld_reason="deadline",
        deadline_missed=True,
        lateness_ms=2.5,
        episode_idx=1,
        reward=0.0,
        safety_violations=["joint_limit"],
    )
    attributes = tick_span_attributes(result, BASE)
    assert attributes[semconv.ATTR_WITHHELD_REASON] == "deadline"
    assert attributes[semconv.ATTR_LATENESS_MS] == 2.5
    assert attributes[semconv.ATTR_EPISODE_IDX] == 1
    assert attributes[semconv.ATTR_REWARD] == 0.0  # zero is a value, not an absence
    assert attributes[semconv.ATTR_SAFETY_VIOLATIONS] == 1
    assert semconv.ATTR_TERMINATED not in attributes


def _every_field_set() -> TickResult:
    """A tick with a value (not the default, not ``None``) in every field."""
    return TickResult(
        tick_idx=3,
        start_ns=5,
        tick_ms=1.0,
        sensors_ms=0.1,
        world_state_ms=0.2,
        inference_ms=0.3,
        safety_ms=0.4,
        hal_ms=0.5,
        action_applied=True,  # a probe, not a plausible tick: every field differs from its default
        withheld_reason="safety",
        safety_violations=["joint_limit", "nan"],
        stale_sensors=["front"],
        deadline_missed=True,
        lateness_ms=0.7,
        requested_action=[1.0],
        sent_action=[0.5],
        trace_context="00-" + "a" * 32 + "-" + "b" * 16 + "-01",
        step_idx=2,
        episode_idx=1,
        reward=0.25,
        terminated=False,
        truncated=True,
        intervention=True,
        active_skill="leader_arm",
        policy_action=[0.75],
        handover_ramp=True,
    )


def test_every_field_with_a_telemetry_name_reaches_the_span() -> None:
    tick = _every_field_set()
    assert set(semconv.TICK_ATTRIBUTES) <= set(TickResult.model_fields), "a table row names no TickResult field"
    unset = [name for name, info in TickResult.model_fields.items() if getattr(tick, name) == info.get_default()]
    assert unset == [], f"the probe leaves {unset} at their defaults"
    attributes = tick_span_attributes(tick, BASE)
    for name, attribute in semconv.TICK_ATTRIBUTES.items():
        expected = len(tick.safety_violations) if name == "safety_violations" else getattr(tick, name)
        assert attributes[attribute] == expected, name
    assert set(attributes) == {*BASE, *semconv.TICK_ATTRIBUTES.values()}


def test_the_attribute_names_are_the_published_ones() -> None:
    # Dashboards and trace queries use these names: derived from the table, never renamed by it.
    assert dict(semconv.TICK_ATTRIBUTES) == {
        "tick_idx": "openral.tick.idx",
        "tick_ms": "skill.tick_ms",
        "sensors_ms": "skill.sensors_ms",
        "world_state_ms": "skill.world_state_ms",
        "inference_ms": "skill.inference_ms",
        "safety_ms": "skill.safety_ms",
        "hal_ms": "skill.hal_ms",
        "action_applied": "skill.action_applied",
        "withheld_reason": "skill.withheld_reason",
        "safety_violations": "skill.safety_violations",
        "lateness_ms": "openral.tick.lateness_ms",
        "step_idx": "skill.step_idx",
        "episode_idx": "skill.episode_idx",
        "reward": "skill.reward",
        "terminated": "skill.terminated",
        "truncated": "skill.truncated",
        "intervention": "openral.takeover.intervention",
        "active_skill": "openral.takeover.active_skill",
        "handover_ramp": "openral.takeover.ramp",
    }
