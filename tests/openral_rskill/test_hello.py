"""HelloSkill: starts at the measured pose, stays inside limits and speed bounds, deterministic."""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from importlib.metadata import entry_points
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.strategies import DrawFn

from openral_core import (
    ControlMode,
    JointKind,
    JointSpec,
    JointState,
    RobotManifest,
    ROSConfigError,
    ROSSkillError,
    RSkillState,
    WorldState,
)
from openral_rskill.chunks import ChunkRequest
from openral_rskill.hello import HelloParams, HelloSkill

MakeWorld = Callable[..., WorldState]
START = [0.1, -0.2, 0.3, -0.4, 0.5, 0.6]
RATE = 100.0


def run(skill: HelloSkill, world: WorldState, steps: int) -> list[list[float]]:
    """Configure and activate if needed, then step ``steps`` times; the rows commanded."""
    if skill.state is RSkillState.UNCONFIGURED:
        skill.configure()
        skill.activate()
    return [skill.step(world).first for _ in range(steps)]


def hello(robot: RobotManifest, rate_hz: float = RATE, **params: Any) -> HelloSkill:
    return HelloSkill.from_config(params, robot=robot, rate_hz=rate_hz)


def test_first_command_is_the_start_pose(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = hello(robot)
    skill.configure()
    skill.activate()
    action = skill.step(make_world(robot.joint_names, START, stamp_ns=42))
    assert action.first == START
    assert action.control_mode is ControlMode.JOINT_POSITION
    assert action.joint_names == robot.joint_names
    assert action.horizon == 1
    assert action.skill_id == "hello"
    assert action.stamp_ns == 42
    assert skill.info.skill_id == "hello"


def test_joint_state_is_matched_by_name(robot: RobotManifest, make_world: MakeWorld) -> None:
    names = [*reversed(robot.joint_names), "conveyor"]
    positions = [*reversed(START), 9.0]
    rows = run(hello(robot), make_world(names, positions), 1)
    assert rows[0] == START


def test_wave_reaches_its_amplitude_after_the_ramp(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = hello(robot, amplitude_rad=0.2, frequency_hz=0.5, ramp_s=0.5, max_speed_fraction=1.0)
    rows = run(skill, make_world(robot.joint_names, START), int(RATE * 3))
    for j, name in enumerate(robot.joint_names):
        excursion = max(abs(row[j] - START[j]) for row in rows)
        if name == "gripper":
            assert excursion == 0.0
        else:
            assert excursion == pytest.approx(0.2, abs=0.005), name


def test_ramp_grows_the_wave_smoothly(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = hello(robot, ramp_s=2.0, frequency_hz=0.5)
    rows = run(skill, make_world(robot.joint_names, START), int(RATE * 4))
    first_second = max(abs(row[0] - START[0]) for row in rows[: int(RATE * 0.5)])
    later = max(abs(row[0] - START[0]) for row in rows[int(RATE * 2) :])
    assert first_second < 0.25 * later


def test_gripper_holds_unless_asked_to_wave(robot: RobotManifest, make_world: MakeWorld) -> None:
    world = make_world(robot.joint_names, START)
    g = robot.joint_names.index("gripper")
    assert {row[g] for row in run(hello(robot), world, 300)} == {START[g]}
    waved = {row[g] for row in run(hello(robot, gripper="wave"), world, 300)}
    assert len(waved) > 100


def test_only_the_listed_joints_move(robot: RobotManifest, make_world: MakeWorld) -> None:
    rows = run(hello(robot, joints=["elbow_flex"]), make_world(robot.joint_names, START), 300)
    for j, name in enumerate(robot.joint_names):
        values = {row[j] for row in rows}
        assert (len(values) > 1) == (name == "elbow_flex"), name


def test_successive_joints_are_phase_shifted(robot: RobotManifest, make_world: MakeWorld) -> None:
    world = make_world(robot.joint_names, [0.0] * 6)
    rows = run(hello(robot, phase_step_rad=math.pi / 2, ramp_s=0.5), world, 300)
    # Joint 0 follows sin(ωt), joint 1 cos(ωt): one crosses zero where the other peaks.
    assert max(abs(row[0] - row[1]) for row in rows) > 0.1
    same = run(hello(robot, phase_step_rad=0.0, ramp_s=0.5), world, 300)
    assert all(row[0] == row[1] for row in same)


def test_is_deterministic_and_ignores_the_pose_after_latching(robot: RobotManifest, make_world: MakeWorld) -> None:
    names = robot.joint_names
    first = run(hello(robot), make_world(names, START), 250)
    skill = hello(robot)
    skill.configure()
    skill.activate()
    moving_worlds = [make_world(names, START)] + [make_world(names, [k * 0.001] * 6) for k in range(1, 250)]
    second = [skill.step(w).first for w in moving_worlds]
    assert first == second


def test_time_axis_is_ticks_not_wall_time(robot: RobotManifest, make_world: MakeWorld) -> None:
    """At 0.25 Hz and 100 Hz ticks the wave (after the ramp) repeats every 400 ticks and inverts every 200."""
    rows = run(hello(robot, ramp_s=1.0), make_world(robot.joint_names, START), 1000)
    for j in range(5):
        assert rows[513][j] == pytest.approx(rows[913][j], abs=1e-12)
        assert abs(rows[513][j] - START[j]) > 1e-3
        assert rows[713][j] == pytest.approx(2 * START[j] - rows[513][j], abs=1e-12)


def test_reset_and_reactivate_latch_the_new_pose(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = hello(robot)
    run(skill, make_world(robot.joint_names, START), 50)
    other = [0.0, 0.0, 0.0, 0.0, 0.0, 0.5]
    skill.reset()
    assert skill.step(make_world(robot.joint_names, other)).first == other
    skill.deactivate()
    skill.activate()
    assert skill.start_pose is None
    assert skill.step(make_world(robot.joint_names, START)).first == START


def test_start_pose_outside_the_limits_is_clamped_onto_them(robot: RobotManifest, make_world: MakeWorld) -> None:
    start = [2.5, -1.75, 0.0, 0.0, 0.0, 1.2]
    rows = run(hello(robot), make_world(robot.joint_names, start), 500)
    assert rows[0] == [1.9, -1.7, 0.0, 0.0, 0.0, 1.0]
    for row in rows:
        for value, spec in zip(row, robot.joints, strict=True):
            assert spec.lower <= value <= spec.upper


def test_amplitude_shrinks_near_a_limit(robot: RobotManifest, make_world: MakeWorld) -> None:
    start = [1.8, 0.0, 0.0, 0.0, 0.0, 0.5]  # 0.1 below shoulder_pan's upper limit
    skill = hello(robot, amplitude_rad=0.5, limit_margin=0.05)
    rows = run(skill, make_world(robot.joint_names, start), 1000)
    assert skill.amplitudes[0] == pytest.approx(0.05)
    assert skill.amplitudes[1] == pytest.approx(0.5), "a joint with room keeps its full amplitude"
    assert max(row[0] for row in rows) <= 1.9 - 0.05 + 1e-12
    assert max(row[0] for row in rows) > 1.84


def test_amplitude_shrinks_to_respect_the_velocity_limit(make_world: MakeWorld) -> None:
    slow = RobotManifest(
        robot_id="slow",
        joints=[JointSpec(name="a", lower=-3.0, upper=3.0, velocity_limit=0.1)],
    )
    skill = hello(slow, amplitude_rad=1.0, frequency_hz=1.0, ramp_s=1.0, max_speed_fraction=0.5)
    rows = run(skill, make_world(["a"], [0.0]), 500)
    ramp_slope = 15 / 8
    expected = 0.5 * 0.1 / math.hypot(2 * math.pi, ramp_slope)
    assert skill.amplitudes == [pytest.approx(expected)]
    steps = [abs(b[0] - a[0]) for a, b in itertools.pairwise(rows)]
    assert max(steps) <= 0.5 * 0.1 / RATE
    assert max(steps) > 0.8 * 0.5 * 0.1 / RATE * (2 * math.pi / math.hypot(2 * math.pi, ramp_slope))


def test_missing_joint_state_latches_a_skill_error(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = hello(robot)
    skill.configure()
    skill.activate()
    with pytest.raises(ROSSkillError, match="no joint_state") as info:
        skill.step(make_world(None))
    assert isinstance(info.value.__cause__, ROSSkillError)
    assert skill.state is RSkillState.ERROR


def test_missing_joint_is_named(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = hello(robot)
    skill.configure()
    skill.activate()
    names = robot.joint_names[:-1]
    with pytest.raises(ROSSkillError, match="gripper"):
        skill.step(make_world(names, START[:-1]))


def test_non_finite_start_pose_is_refused(robot: RobotManifest, make_world: MakeWorld) -> None:
    skill = hello(robot)
    skill.configure()
    skill.activate()
    with pytest.raises(ROSSkillError, match="non-finite"):
        skill.step(make_world(robot.joint_names, [math.nan, *START[1:]]))


@pytest.mark.parametrize(
    ("params", "field", "text"),
    [
        ({"amplitude": 0.1}, "amplitude", "allowed keys: amplitude_rad"),
        ({"amplitude_rad": -0.1}, "amplitude_rad", "greater than or equal to 0"),
        ({"frequency_hz": 0.0}, "frequency_hz", "greater than 0"),
        ({"frequency_hz": 50.0}, "frequency_hz", "below 50 Hz"),
        ({"ramp_s": 0.0}, "ramp_s", "greater than 0"),
        ({"max_speed_fraction": 1.5}, "max_speed_fraction", "less than or equal to 1"),
        ({"amplitude_rad": float("nan")}, "amplitude_rad", "finite"),
        ({"amplitude_rad": "0.2"}, "amplitude_rad", "got text"),
        ({"amplitude_rad": True}, "amplitude_rad", "booleans are not numbers"),
        ({"gripper": "open"}, "gripper", "'hold' or 'wave'"),
        ({"joints": ["elbow"]}, "joints", "its joints are shoulder_pan"),
        ({"joints": ["elbow_flex", "elbow_flex"]}, "joints", "repeats"),
        ({"joints": ["gripper"]}, "joints", "gripper: wave"),
    ],
)
def test_param_errors_name_the_field(robot: RobotManifest, params: dict[str, Any], field: str, text: str) -> None:
    with pytest.raises(ROSConfigError) as info:
        hello(robot, **params)
    assert info.value.field == f"vla.params.{field}"
    assert text in str(info.value)


def test_gripper_may_be_listed_when_it_waves(robot: RobotManifest) -> None:
    hello(robot, joints=["gripper"], gripper="wave")


def test_bad_rate_is_refused(robot: RobotManifest) -> None:
    with pytest.raises(ROSConfigError, match="rate_hz"):
        hello(robot, rate_hz=0.0)


def test_registered_as_the_hello_plugin() -> None:
    (entry,) = entry_points(group="openral.skills", name="hello")
    assert entry.load() is HelloSkill


# -- property: limits, smoothness and the start pose, for generated robots, poses and params ----------


@st.composite
def scenarios(draw: DrawFn) -> tuple[RobotManifest, list[float], HelloParams, float]:
    n = draw(st.integers(min_value=1, max_value=7))
    joints = []
    start = []
    for j in range(n):
        lower = draw(st.floats(min_value=-4.0, max_value=3.0))
        upper = lower + draw(st.floats(min_value=1e-3, max_value=6.0))
        kind = draw(st.sampled_from([JointKind.REVOLUTE, JointKind.REVOLUTE, JointKind.GRIPPER]))
        velocity = draw(st.floats(min_value=0.01, max_value=10.0))
        joints.append(JointSpec(name=f"j{j}", kind=kind, lower=lower, upper=upper, velocity_limit=velocity))
        span = upper - lower
        start.append(draw(st.floats(min_value=lower - 0.1 * span, max_value=upper + 0.1 * span)))
    rate = draw(st.sampled_from([10.0, 30.0, 100.0, 500.0]))
    params = HelloParams(
        amplitude_rad=draw(st.floats(min_value=0.0, max_value=3.0)),
        frequency_hz=draw(st.floats(min_value=0.05, max_value=rate / 2 * 0.99)),
        ramp_s=draw(st.floats(min_value=0.01, max_value=2.0)),
        phase_step_rad=draw(st.floats(min_value=-math.pi, max_value=math.pi)),
        gripper=draw(st.sampled_from(["hold", "wave"])),
        max_speed_fraction=draw(st.floats(min_value=0.05, max_value=1.0)),
        limit_margin=draw(st.floats(min_value=0.0, max_value=0.3)),
    )
    return RobotManifest(robot_id="generated", joints=joints), start, params, rate


@settings(max_examples=150, deadline=None)
@given(scenario=scenarios())
def test_never_leaves_the_limits_never_jumps_and_starts_at_the_start_pose(
    scenario: tuple[RobotManifest, list[float], HelloParams, float],
) -> None:
    robot, start, params, rate = scenario
    names = robot.joint_names
    world = WorldState(stamp_ns=0, joint_state=JointState(names=names, positions=start))
    skill = HelloSkill(robot, rate_hz=rate, params=params)
    steps = min(1500, math.ceil((params.ramp_s + 1.0 / params.frequency_hz) * rate) + 2)
    rows = run(skill, world, steps)

    clamped = [min(max(q, spec.lower), spec.upper) for q, spec in zip(start, robot.joints, strict=True)]
    assert rows[0] == clamped
    assert skill.start_pose == clamped
    # The envelope itself, not only the sampled points: centre ± amplitude stays inside the limits.
    for c, a, spec in zip(clamped, skill.amplitudes, robot.joints, strict=True):
        assert spec.lower <= c - a
        assert c + a <= spec.upper
    for row in rows:
        for value, spec in zip(row, robot.joints, strict=True):
            assert spec.lower <= value <= spec.upper
    for j, spec in enumerate(robot.joints):
        bound = params.max_speed_fraction * spec.velocity_limit / rate
        worst = max(abs(b[j] - a[j]) for a, b in itertools.pairwise(rows)) if len(rows) > 1 else 0.0
        assert worst <= bound * (1 + 1e-9) + 1e-12, spec.name
        if spec.kind is JointKind.GRIPPER and params.gripper == "hold":
            assert all(row[j] == clamped[j] for row in rows)


def test_a_chunk_holds_the_wave_of_the_ticks_after_its_observation(robot: RobotManifest, make_world: MakeWorld) -> None:
    per_tick = run(hello(robot), make_world(robot.joint_names, START), 60)
    chunked = hello(robot, chunk_size=10)
    assert chunked.info.chunk_size == 10
    chunked.configure()
    chunked.activate()
    period_ns = round(1e9 / RATE)
    for tick in (0, 7, 35):  # observations at ticks 0, 7 and 35 of the episode (stamps are what count)
        action = chunked.step(make_world(robot.joint_names, START, stamp_ns=1_000 + tick * period_ns))
        assert action.horizon == 10
        for j, row in enumerate(action.targets):
            assert row == pytest.approx(per_tick[tick + j], abs=1e-12)


def test_the_chunk_executor_gets_the_same_chunk_as_one_array(robot: RobotManifest, make_world: MakeWorld) -> None:
    stepped, chunked = hello(robot, chunk_size=5), hello(robot, chunk_size=5)
    for skill in (stepped, chunked):
        skill.configure()
        skill.activate()
    world = make_world(robot.joint_names, START, stamp_ns=1_000)
    rows = chunked.step_chunk(ChunkRequest(world))
    assert isinstance(rows, np.ndarray)
    assert rows.shape == (5, len(robot.joint_names))
    np.testing.assert_array_equal(rows, stepped.step(world).targets)
