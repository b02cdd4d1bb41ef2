"""EnvelopeSafetyClient: nothing outside the joint limits or the per-tick step limit gets through."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openral_core import (
    Action,
    ControlMode,
    JointSpec,
    JointState,
    RobotManifest,
    ROSSafetyViolation,
    SafetyConfig,
    SafetyMode,
)
from openral_runner.envelope import EnvelopeSafetyClient

RATE = 30.0
ROBOT = RobotManifest(
    robot_id="arm",
    joints=[
        JointSpec(name="a", lower=-1.0, upper=1.0, velocity_limit=3.0),
        JointSpec(name="b", lower=-0.5, upper=2.0, velocity_limit=1.5),
        JointSpec(name="g", kind="gripper", lower=0.0, upper=1.0, velocity_limit=6.0),
    ],
)
NAMES = ROBOT.joint_names
MAX_STEP = [j.velocity_limit / RATE for j in ROBOT.joints]

values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(min_value=-3, max_value=3),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308]),
)
rows = st.lists(values, min_size=3, max_size=3)
names = st.one_of(st.just(NAMES), st.lists(st.sampled_from(["a", "b", "g", "x"]), min_size=1, max_size=4))


def action(row: list[float], joint_names: list[str] = NAMES, mode: ControlMode = ControlMode.JOINT_POSITION) -> Action:
    return Action(control_mode=mode, joint_names=joint_names, targets=[row])


def client(mode: SafetyMode) -> EnvelopeSafetyClient:
    return EnvelopeSafetyClient.from_config(SafetyConfig(mode=mode), robot=ROBOT, rate_hz=RATE)


@pytest.mark.parametrize("mode", list(SafetyMode))
@settings(max_examples=300, deadline=None)
@given(sequence=st.lists(st.tuples(names, st.lists(values, min_size=1, max_size=4)), min_size=1, max_size=30))
def test_nothing_outside_the_envelope_is_ever_sent(mode: SafetyMode, sequence: list) -> None:
    safety = client(mode)
    safety.observe_state(JointState(names=NAMES, positions=[0.0, 0.0, 0.5]))
    sent: list[list[float]] = []
    reference = [0.0, 0.0, 0.5]
    for joint_names, row in sequence:
        if len(row) != len(joint_names):
            continue  # such an Action cannot even be constructed
        try:
            replacement = safety.check_action(action(row, joint_names))
        except ROSSafetyViolation:
            continue
        out = action(row, joint_names) if replacement is None else replacement
        assert out.joint_names == NAMES
        assert out.horizon == 1
        checked = out.first
        for i, value in enumerate(checked):
            assert math.isfinite(value)
            assert ROBOT.joints[i].lower <= value <= ROBOT.joints[i].upper
            assert abs(value - reference[i]) <= MAX_STEP[i] + 1e-12
        safety.commit(out)
        reference = checked
        sent.append(checked)


def test_clamp_mode_clips_to_limits_and_step() -> None:
    safety = client(SafetyMode.CLAMP)
    safety.observe_state(JointState(names=NAMES, positions=[0.9, 0.0, 0.5]))
    out = safety.check_action(action([5.0, -5.0, 0.5]))
    assert out is not None
    assert out.first == pytest.approx([1.0, -MAX_STEP[1], 0.5])


def test_reject_mode_names_the_check() -> None:
    safety = client(SafetyMode.REJECT)
    safety.observe_state(JointState(names=NAMES, positions=[0.0, 0.0, 0.5]))
    with pytest.raises(ROSSafetyViolation) as info:
        safety.check_action(action([1.5, 0.0, 0.5]))
    assert info.value.check_name == "joint_limit"
    with pytest.raises(ROSSafetyViolation) as info:
        safety.check_action(action([0.5, 0.0, 0.5]))
    assert info.value.check_name == "step"


def test_non_finite_and_wrong_joints_and_modes_are_always_rejected() -> None:
    for mode in SafetyMode:
        safety = client(mode)
        with pytest.raises(ROSSafetyViolation, match="nan") as info:
            safety.check_action(action([math.nan, 0.0, 0.5]))
        assert info.value.check_name == "non_finite"
        with pytest.raises(ROSSafetyViolation) as info:
            safety.check_action(action([0.0, 0.0], ["a", "b"]))
        assert info.value.check_name == "joint_names"
        with pytest.raises(ROSSafetyViolation) as info:
            safety.check_action(action([0.0, 0.0, 0.0], mode=ControlMode.JOINT_TORQUE))
        assert info.value.check_name == "control_mode"


def test_in_envelope_action_passes_unchanged() -> None:
    safety = client(SafetyMode.REJECT)
    safety.observe_state(JointState(names=NAMES, positions=[0.0, 0.0, 0.5]))
    assert safety.check_action(action([0.05, 0.01, 0.6])) is None


def test_chunk_is_cut_to_the_checked_row() -> None:
    safety = client(SafetyMode.CLAMP)
    chunk = Action(joint_names=NAMES, targets=[[0.0, 0.0, 0.5], [0.9, 1.9, 0.0]])
    out = safety.check_action(chunk)
    assert out is not None
    assert out.targets == [[0.0, 0.0, 0.5]]
