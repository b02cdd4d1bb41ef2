"""Action and SafetyEnvelope: round trips, rectangular targets, non-finite values, the workspace box."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from openral_core import Action, ControlMode, SafetyEnvelope

PROPERTY = settings(max_examples=80, deadline=None)
finite = st.floats(allow_nan=False, allow_infinity=False)
positive = st.floats(min_value=1e-6, max_value=1e6, allow_nan=False)


@st.composite
def actions(draw: st.DrawFn, values: st.SearchStrategy[float] = finite) -> Action:
    names = draw(st.lists(st.text(max_size=8), max_size=6))
    n = len(names)
    horizon = draw(st.integers(1, 5))
    return Action(
        control_mode=draw(st.sampled_from(list(ControlMode))),
        joint_names=names,
        targets=draw(st.lists(st.lists(values, min_size=n, max_size=n), min_size=horizon, max_size=horizon)),
        confidence=draw(st.none() | st.lists(finite, max_size=5)),
        stamp_ns=draw(st.integers(0, 2**63 - 1)),
        skill_id=draw(st.none() | st.text(max_size=10)),
    )


@st.composite
def envelopes(draw: st.DrawFn) -> SafetyEnvelope:
    box: dict[str, Any] = {}
    if draw(st.booleans()):
        coordinate = st.floats(min_value=-100.0, max_value=100.0)
        lo = draw(st.tuples(coordinate, coordinate, coordinate))
        size = draw(st.tuples(*[st.floats(min_value=1e-3, max_value=100.0)] * 3))
        box = {"workspace_min": lo, "workspace_max": tuple(a + s for a, s in zip(lo, size, strict=True))}
    return SafetyEnvelope(
        max_ee_speed_m_s=draw(positive),
        max_force_n=draw(positive),
        max_joint_speed_factor=draw(st.floats(min_value=1e-6, max_value=1.0)),
        **box,
    )


def _same(a: list[list[float]], b: list[list[float]]) -> bool:
    return all(
        (math.isnan(x) and math.isnan(y)) or x == y
        for row_a, row_b in zip(a, b, strict=True)
        for x, y in zip(row_a, row_b, strict=True)
    )


@PROPERTY
@given(actions())
def test_action_round_trips(action: Action) -> None:
    assert Action.model_validate_json(action.model_dump_json()) == action
    assert Action.model_validate(action.model_dump()) == action


@PROPERTY
@given(envelopes())
def test_envelope_round_trips(envelope: SafetyEnvelope) -> None:
    assert SafetyEnvelope.model_validate_json(envelope.model_dump_json()) == envelope
    assert SafetyEnvelope.model_validate(envelope.model_dump()) == envelope


def test_action_accepts_non_finite_values_so_safety_can_reject_them() -> None:
    action = Action(joint_names=["a", "b", "c"], targets=[[math.nan, math.inf, -math.inf]])
    assert math.isnan(action.first[0])
    assert action.first[1:] == [math.inf, -math.inf]


@PROPERTY
@given(actions(values=st.floats()))
def test_non_finite_values_survive_a_json_round_trip(action: Action) -> None:
    text = action.model_dump_json()
    try:
        back = Action.model_validate_json(text)
    except ValidationError as exc:
        pytest.fail(
            f"an Action with non-finite targets cannot be read back from its own JSON ({text}): pydantic writes "
            f"NaN/Inf as null by default; set ser_json_inf_nan='constants' on Action. {exc.errors()[0]['msg']}"
        )
    assert _same(back.targets, action.targets)


def test_targets_must_be_rectangular() -> None:
    with pytest.raises(ValidationError, match=r"targets\[1\] has 1 values for 2 joint names"):
        Action(joint_names=["a", "b"], targets=[[0.0, 1.0], [0.0]])


def test_action_needs_at_least_one_step() -> None:
    with pytest.raises(ValidationError, match="targets"):
        Action(joint_names=["a"], targets=[])


def test_horizon_and_first_step() -> None:
    chunk = Action(joint_names=["a"], targets=[[1.0], [2.0], [3.0]])
    assert chunk.horizon == 3
    assert chunk.first == [1.0]
    assert chunk.control_mode is ControlMode.JOINT_POSITION


def test_action_stamp_is_not_negative() -> None:
    with pytest.raises(ValidationError, match="stamp_ns"):
        Action(joint_names=["a"], targets=[[0.0]], stamp_ns=-1)


# --- SafetyEnvelope -------------------------------------------------------------------------------


def test_workspace_bounds_go_together() -> None:
    with pytest.raises(ValidationError, match="workspace_min and workspace_max must be given together"):
        SafetyEnvelope(workspace_min=(0.0, 0.0, 0.0))
    with pytest.raises(ValidationError, match="workspace_min and workspace_max must be given together"):
        SafetyEnvelope(workspace_max=(1.0, 1.0, 1.0))


@pytest.mark.parametrize(("axis", "index"), [("x", 0), ("y", 1), ("z", 2)])
def test_workspace_min_must_be_below_max_on_every_axis(axis: str, index: int) -> None:
    high = [1.0, 1.0, 1.0]
    high[index] = 0.0
    with pytest.raises(ValidationError, match=rf"workspace_min\.{axis} \(0\.0\) must be below workspace_max\.{axis}"):
        SafetyEnvelope(workspace_min=(0.0, 0.0, 0.0), workspace_max=tuple(high))  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(("axis", "index"), [("x", 0), ("y", 1), ("z", 2)])
@pytest.mark.parametrize("corner", ["workspace_min", "workspace_max"])
def test_workspace_bound_must_be_finite(bad: float, axis: str, index: int, corner: str) -> None:
    # Every comparison with NaN is false, so without this check `lo >= hi` passes and a box check
    # like `p < lo or p > hi` never fires.
    corners = {"workspace_min": [0.0, 0.0, 0.0], "workspace_max": [1.0, 1.0, 1.0]}
    corners[corner][index] = bad
    with pytest.raises(ValidationError, match=rf"workspace bounds on {axis} must be finite"):
        SafetyEnvelope(**{k: tuple(v) for k, v in corners.items()})  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "fields",
    [
        {"max_ee_speed_m_s": 0.0},
        {"max_force_n": -1.0},
        {"max_force_n": math.nan},
        {"max_joint_speed_factor": 0.0},
        {"max_joint_speed_factor": 1.5},
    ],
)
def test_envelope_limits_are_positive(fields: dict[str, float]) -> None:
    with pytest.raises(ValidationError, match=next(iter(fields))):
        SafetyEnvelope(**fields)
