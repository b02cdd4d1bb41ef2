"""Tick span attributes: timings always, outcome fields only when they apply."""

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
