"""TickContext: the tick's facts in one place; its TickResult equals a validated one, field for field."""

from __future__ import annotations

import json

from openral_core import TickResult, WithheldReason
from openral_runner.tick_context import TickContext


def test_result_is_the_validated_result_without_validation() -> None:
    tick = TickContext(7, 12.5, 12.6)
    tick.sensors_ms, tick.world_state_ms, tick.inference_ms, tick.safety_ms, tick.hal_ms = 0.1, 0.2, 0.3, 0.4, 0.5
    tick.withhold(WithheldReason.SAFETY)
    tick.withhold(WithheldReason.DEADLINE)  # the first reason stands
    tick.safety_violations.append("joint_limit")
    tick.requested_action = [1.0, 2.0]
    tick.lateness_ms = 0.25
    tick.step_idx, tick.episode_idx, tick.reward = 3, 1, 0.5
    fast = tick.result(tick_ms=1.5, trace_context="00-abc-def-01")
    validated = TickResult.model_validate(fast.model_dump())
    assert fast == validated
    assert set(fast.__dict__) == set(TickResult.model_fields), "every field is set, none defaulted"
    assert fast.withheld_reason is WithheldReason.SAFETY
    assert fast.deadline_missed
    assert fast.start_ns == 12_500_000_000
    assert json.loads(fast.model_dump_json())["safety_violations"] == ["joint_limit"]
    assert fast.model_dump(exclude_unset=True) == fast.model_dump()


def test_each_context_has_its_own_lists() -> None:
    first, second = TickContext(0, 0.0, 1.0), TickContext(1, 1.0, 2.0)
    first.stale_sensors.append("front")
    assert second.stale_sensors == []


def test_every_result_field_is_read_off_the_context_and_the_contexts_own_stay_behind() -> None:
    tick = TickContext(2, 1.0, 1.1)
    tick.terminated, tick.truncated = True, False
    values = tick.result(tick_ms=0.5, trace_context=None).__dict__
    assert set(values) == set(TickResult.model_fields)
    for own in ("start_s", "deadline_s", "withheld", "deadline_checked", "world"):
        assert own not in values
    for name in TickResult.model_fields:
        if hasattr(tick, name):
            assert values[name] is getattr(tick, name), f"{name} is not the context's own value"
    assert values["start_ns"] == 1_000_000_000
    assert values["deadline_missed"] is False
