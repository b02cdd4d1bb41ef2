"""TickResult and RunResult: round trips, only what applies in a dump without None, and non-finite actions."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from openral_core import RunResult, TickResult

PROPERTY = settings(max_examples=80, deadline=None)
finite = st.floats(allow_nan=False, allow_infinity=False)
non_negative = st.floats(min_value=0.0, allow_infinity=False)
counts = st.integers(0, 2**40)
SIM_FIELDS = {"step_idx", "episode_idx", "reward", "terminated", "truncated"}

tick_results = st.builds(
    TickResult,
    tick_idx=counts,
    start_ns=st.integers(0, 2**63 - 1),
    tick_ms=finite,
    sensors_ms=finite,
    world_state_ms=finite,
    inference_ms=finite,
    safety_ms=finite,
    hal_ms=finite,
    action_applied=st.booleans(),
    withheld_reason=st.none() | st.sampled_from(["deadline", "safety", "stale_sensor", "skill_error"]),
    safety_violations=st.lists(st.text(max_size=10), max_size=3),
    stale_sensors=st.lists(st.text(max_size=10), max_size=3),
    deadline_missed=st.booleans(),
    lateness_ms=finite,
    requested_action=st.none() | st.lists(finite, max_size=6),
    sent_action=st.none() | st.lists(finite, max_size=6),
    trace_context=st.none() | st.text(max_size=55),
    step_idx=st.none() | counts,
    episode_idx=st.none() | counts,
    reward=st.none() | finite,
    terminated=st.none() | st.booleans(),
    truncated=st.none() | st.booleans(),
)

run_results = st.builds(
    RunResult,
    runner_name=st.text(max_size=12),
    skill_id=st.none() | st.text(max_size=12),
    rate_hz=st.floats(min_value=1e-3, max_value=1e5),
    n_ticks=counts,
    duration_s=non_negative,
    effective_rate_hz=non_negative,
    tick_ms_mean=finite,
    tick_ms_p50=finite,
    tick_ms_p99=finite,
    tick_ms_max=finite,
    inference_ms_mean=finite,
    inference_ms_p99=finite,
    start_jitter_us_p99=finite,
    overhead_us_mean=finite,
    missed_slots=counts,
    deadline_misses=counts,
    budget_violations=counts,
    dropped_actions=counts,
    withheld_actions=counts,
    stale_reads=counts,
    safety_violations=counts,
    failed_ticks=counts,
    stop_reason=st.sampled_from(["max_ticks", "duration", "terminated", "stop_requested", "deadline", "estop"]),
    trace_id=st.none() | st.from_regex(r"[0-9a-f]{32}", fullmatch=True),
    metadata=st.dictionaries(
        st.text(max_size=6), st.none() | st.booleans() | st.integers(-100, 100) | st.text(max_size=6)
    ),
)


@PROPERTY
@given(tick_results)
def test_tick_result_round_trips(tick: TickResult) -> None:
    assert TickResult.model_validate_json(tick.model_dump_json()) == tick
    assert TickResult.model_validate(tick.model_dump()) == tick


@PROPERTY
@given(run_results)
def test_run_result_round_trips(run: RunResult) -> None:
    assert RunResult.model_validate_json(run.model_dump_json()) == run
    assert RunResult.model_validate(run.model_dump()) == run


def test_a_hardware_tick_outside_an_episode_dumps_no_optional_field() -> None:
    tick = TickResult(tick_idx=3, tick_ms=2.0, action_applied=True, requested_action=[0.1], sent_action=[0.1])
    dumped = tick.model_dump(exclude_none=True)
    assert not SIM_FIELDS & set(dumped), f"sim fields leaked into a hardware tick: {SIM_FIELDS & set(dumped)}"
    assert "trace_context" not in dumped
    assert "withheld_reason" not in dumped
    assert dumped["tick_idx"] == 3
    assert dumped["action_applied"] is True


def test_sim_tick_carries_its_fields() -> None:
    tick = TickResult(tick_idx=0, step_idx=4, episode_idx=1, reward=0.5, terminated=False, truncated=False)
    dumped = tick.model_dump(exclude_none=True)
    assert {k: dumped[k] for k in SIM_FIELDS} == {
        "step_idx": 4,
        "episode_idx": 1,
        "reward": 0.5,
        "terminated": False,
        "truncated": False,
    }


def test_trace_context_appears_when_set() -> None:
    context = "00-" + "a" * 32 + "-" + "b" * 16 + "-01"
    assert TickResult(tick_idx=0, trace_context=context).model_dump(exclude_none=True)["trace_context"] == context


def test_rejected_non_finite_action_survives_json() -> None:
    tick = TickResult(tick_idx=0, withheld_reason="safety", requested_action=[math.nan, math.inf, 0.5])
    text = tick.model_dump_json()
    try:
        back = TickResult.model_validate_json(text)
    except ValidationError:
        pytest.fail(
            f"a tick whose NaN/Inf action was rejected cannot be read back from its own JSON ({text}): pydantic "
            "writes NaN/Inf as null; set ser_json_inf_nan='constants' on TickResult (and Action)"
        )
    assert back.requested_action is not None
    assert math.isnan(back.requested_action[0])
    assert back.requested_action[1:] == [math.inf, 0.5]


@pytest.mark.parametrize(
    ("model", "fields"),
    [
        (TickResult, {"tick_idx": -1}),
        (RunResult, {"rate_hz": 0.0, "n_ticks": 1}),
        (RunResult, {"rate_hz": 30.0, "n_ticks": -1}),
        (RunResult, {"rate_hz": 30.0, "n_ticks": 1, "missed_slots": -1}),
        (RunResult, {"rate_hz": 30.0, "n_ticks": 1, "duration_s": -0.5}),
    ],
)
def test_counts_and_rates_are_not_negative(model: type[Any], fields: dict[str, Any]) -> None:
    with pytest.raises(ValidationError):
        model(**fields)


@pytest.mark.parametrize(
    ("model", "valid"), [(TickResult, {"tick_idx": 0}), (RunResult, {"rate_hz": 1.0, "n_ticks": 0})]
)
def test_unknown_field_is_rejected(model: type[Any], valid: dict[str, Any]) -> None:
    model.model_validate(valid)
    with pytest.raises(ValidationError, match="tick_duration"):
        model.model_validate({**valid, "tick_duration": 1.0})


@pytest.mark.parametrize("field", ["tick_idx", "step_idx", "episode_idx"])
def test_indices_are_never_negative(field: str) -> None:
    values = {"tick_idx": 0, field: -1}
    with pytest.raises(ValidationError, match=field):
        TickResult(**values)
