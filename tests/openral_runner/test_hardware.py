"""HardwareRunner: the five-phase tick, faults withheld before actuation, rollback, e-stop."""

from __future__ import annotations

import itertools
import threading
from collections.abc import Iterator

import numpy as np
import pytest

from openral_core import (
    Action,
    DeadlineOverrunPolicy,
    JointState,
    ObserverContext,
    ROSConfigError,
    ROSEStopRequested,
    ROSHardwareError,
    ROSRuntimeError,
    ROSSafetyViolation,
    ROSStopRequested,
    SafetyEnvelope,
    SensorReaderConfig,
    StopReason,
    WithheldReason,
)
from openral_hal.testing import RecordingHAL
from openral_observability.observer import TickObserver
from openral_rskill.testing import ScriptedSkill
from openral_runner.clock import SystemClock
from openral_runner.hardware import HardwareRunner
from openral_runner.safety import SafetyClient, SafetyCommitListener, SafetyStateObserver
from openral_runner.testing import FakeClock, ScriptedReader
from openral_runner.thumbnails import ThumbnailPublisher
from openral_world_state import WorldStateAggregator

JOINTS = ["j0", "j1", "j2"]
CONTEXT = ObserverContext(robot_id="test_arm", rate_hz=30.0)
RATE = 30.0
PERIOD = 1.0 / RATE


class RejectingSafety(SafetyClient):
    """Rejects the actions whose first target is negative; e-stops on a target of 99."""

    envelope = SafetyEnvelope()

    def __init__(self) -> None:
        self.checked: list[Action] = []

    def check_action(self, action: Action) -> Action | None:
        self.checked.append(action)
        if action.first[0] == 99.0:
            raise ROSEStopRequested("operator pressed the stop button")
        if action.first[0] < 0:
            raise ROSSafetyViolation(f"j0 target {action.first[0]} below 0", check_name="joint_limit")
        return None


class HalvingSafety(SafetyClient):
    """Replaces each action with one whose targets are halved (a clamping client)."""

    envelope = SafetyEnvelope()

    def check_action(self, action: Action) -> Action | None:
        return action.model_copy(update={"targets": [[v / 2 for v in action.first]]})


def rows(*values: float) -> list[list[float]]:
    return [[v, 0.0, 0.0] for v in values]


_built: list[HardwareRunner] = []


@pytest.fixture(autouse=True)
def _deactivate_runners() -> Iterator[None]:
    """Deactivate every runner a test built: its telemetry worker flushes here, not into a later test."""
    yield
    while _built:
        _built.pop().deactivate()


def build(
    clock: FakeClock,
    *,
    skill: ScriptedSkill | None = None,
    readers: list[ScriptedReader] | None = None,
    sensor_configs: list[SensorReaderConfig] | None = None,
    hal: RecordingHAL | None = None,
    safety: object | None = None,
    **kwargs: object,
) -> tuple[HardwareRunner, RecordingHAL, ScriptedSkill]:
    hal = hal or RecordingHAL(JOINTS, clock_ns=clock.now_ns)
    skill = skill or ScriptedSkill(JOINTS)
    skill.configure()
    skill.activate()
    aggregator = WorldStateAggregator(joint_max_age_ms=100.0, sensors=sensor_configs or [], clock=clock.now_ns)
    kwargs.setdefault("thumbnail_hz", 0.0)
    runner = HardwareRunner(
        hal=hal,
        skill=skill,
        aggregator=aggregator,
        sensor_readers=readers or [],
        safety_client=safety,  # type: ignore[arg-type]
        rate_hz=RATE,
        clock=clock,
        **kwargs,  # type: ignore[arg-type]
    )
    _built.append(runner)
    return runner, hal, skill


def test_tick_runs_five_phases_and_sends_the_action() -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, actions=rows(0.1, 0.2), on_step=lambda _i: clock.advance(0.005))
    runner, hal, _ = build(clock, skill=skill)
    runner.activate()
    result = runner.run(2)
    assert result.n_ticks == 2
    assert [a.first[0] for a in hal.sent] == [0.1, 0.2]
    tick = runner.recent_ticks[0]
    assert tick.action_applied
    assert tick.inference_ms == pytest.approx(5.0)
    assert tick.sent_action == [0.1, 0.0, 0.0]
    # The skill saw the measured joint state read in this very tick.
    assert skill.seen[1].joint_state is not None
    assert skill.seen[1].joint_state.positions == [0.1, 0.0, 0.0]
    assert hal.calls[:3] == ["connect", "read_state", "send_action"]


def test_each_phase_is_timed_where_it_runs() -> None:
    clock = FakeClock()

    class SlowReadHAL(RecordingHAL):
        def read_state(self) -> JointState:
            clock.advance(0.001)
            return super().read_state()

    hal = SlowReadHAL(JOINTS, clock_ns=clock.now_ns, on_send=lambda _a: clock.advance(0.002))
    skill = ScriptedSkill(JOINTS, actions=rows(0.1), on_step=lambda _i: clock.advance(0.005))
    runner, _, _ = build(clock, skill=skill, hal=hal)
    runner.activate()
    runner.run(1)
    tick = runner.recent_ticks[0]
    # Reading the robot's state is sensing, before the skill is asked; sending the action is the HAL's phase.
    assert (tick.sensors_ms, tick.inference_ms, tick.hal_ms) == pytest.approx((1.0, 5.0, 2.0))
    assert (tick.world_state_ms, tick.safety_ms) == pytest.approx((0.0, 0.0))
    assert tick.tick_ms == pytest.approx(8.0)


def test_frames_reach_the_skill_without_copy() -> None:
    clock = FakeClock()
    cams = [ScriptedReader("front", clock, width=8, height=6), ScriptedReader("wrist", clock, width=4, height=2)]
    configs = [SensorReaderConfig(sensor_id="front"), SensorReaderConfig(sensor_id="wrist")]
    runner, _, skill = build(clock, readers=cams, sensor_configs=configs)
    runner.activate()
    runner.run(3)
    frames = skill.seen[-1].image_frames
    assert frames is not None
    assert set(frames) == {"front", "wrist"}
    assert frames["front"].as_array().shape == (6, 8, 3)
    assert np.shares_memory(frames["front"].as_array(), np.frombuffer(cams[0]._pixels, np.uint8))


def test_rejecting_safety_client_withholds_and_loop_continues() -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, actions=rows(0.1, -0.5, 0.3))
    safety = RejectingSafety()
    runner, hal, _ = build(clock, skill=skill, safety=safety)
    runner.activate()
    result = runner.run(3)
    assert [a.first[0] for a in hal.sent] == [0.1, 0.3]
    assert result.n_ticks == 3
    assert result.safety_violations == 1
    rejected = runner.recent_ticks[1]
    assert not rejected.action_applied
    assert rejected.withheld_reason == "safety"
    assert rejected.safety_violations == ["joint_limit"]
    assert rejected.requested_action == [-0.5, 0.0, 0.0]
    assert rejected.sent_action is None


def test_clamping_client_records_requested_and_sent() -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, actions=rows(0.8))
    runner, hal, _ = build(clock, skill=skill, safety=HalvingSafety())
    runner.activate()
    runner.run(1)
    tick = runner.recent_ticks[0]
    assert tick.requested_action == [0.8, 0.0, 0.0]
    assert tick.sent_action == [0.4, 0.0, 0.0]
    assert hal.sent[0].first == [0.4, 0.0, 0.0]


class SpecOnlySafety:
    """Exactly the specification's ``SafetyClient``: an envelope and ``check_action``, no openral base class."""

    envelope = SafetyEnvelope()

    def __init__(self) -> None:
        self.checked: list[list[float]] = []

    def check_action(self, action: Action) -> Action | None:
        self.checked.append(action.first)
        if action.first[0] < 0:
            raise ROSSafetyViolation("j0 below 0", check_name="joint_limit")
        return None


class StatefulSafety(HalvingSafety):
    """A clamping client that also takes the optional hooks: what it observed and what was sent."""

    def __init__(self) -> None:
        self.observed: list[list[float]] = []
        self.committed: list[list[float]] = []

    def observe_state(self, state: JointState) -> None:
        self.observed.append(list(state.positions))

    def commit(self, action: Action) -> None:
        self.committed.append(action.first)


def test_a_client_with_only_the_specified_protocol_drives_the_runner() -> None:
    clock = FakeClock()
    safety = SpecOnlySafety()
    assert isinstance(safety, SafetyClient)
    assert not isinstance(safety, SafetyStateObserver | SafetyCommitListener)
    skill = ScriptedSkill(JOINTS, actions=rows(0.1, 0.2, -0.5, 0.3, 0.4))
    configs = [SensorReaderConfig(sensor_id="front")]
    runner, hal, _ = build(
        clock, skill=skill, safety=safety, readers=[ScriptedReader("front", clock)], sensor_configs=configs
    )
    runner.activate()
    result = runner.run(5)
    assert result.n_ticks == 5
    assert result.failed_ticks == 0
    assert safety.checked == [[v, 0.0, 0.0] for v in (0.1, 0.2, -0.5, 0.3, 0.4)]
    assert [a.first[0] for a in hal.sent] == [0.1, 0.2, 0.3, 0.4]
    assert [t.withheld_reason for t in runner.recent_ticks] == [None, None, "safety", None, None]


def test_optional_safety_hooks_see_every_measured_state_and_only_sent_actions() -> None:
    clock = FakeClock()
    safety = StatefulSafety()
    skill = ScriptedSkill(JOINTS, actions=rows(0.8, 0.4))
    runner, hal, _ = build(clock, skill=skill, safety=safety)
    runner.activate()
    runner.run(2)
    assert safety.observed == [[0.0, 0.0, 0.0], [0.4, 0.0, 0.0]]  # measured before each step
    assert safety.committed == [a.first for a in hal.sent] == [[0.4, 0.0, 0.0], [0.2, 0.0, 0.0]]  # the replacement


def test_a_safety_client_assigned_later_brings_its_own_hooks() -> None:
    clock = FakeClock()
    first = StatefulSafety()
    runner, _, _ = build(clock, skill=ScriptedSkill(JOINTS, actions=rows(0.1, 0.2, 0.3)), safety=first)
    runner.activate()
    runner.run(1)
    runner.safety_client = SpecOnlySafety()
    runner.run(1)
    second = StatefulSafety()
    runner.safety_client = second
    runner.run(1)
    assert (len(first.observed), len(first.committed)) == (1, 1)
    assert second.committed == [[0.15, 0.0, 0.0]]


def test_estop_stops_loop_and_calls_hal_estop() -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, actions=rows(0.1, 99.0, 0.2, 0.3))
    runner, hal, _ = build(clock, skill=skill, safety=RejectingSafety())
    runner.activate()
    result = runner.run(10)
    assert result.stop_reason == "estop"
    assert result.n_ticks == 2
    assert hal.estop_calls == 1
    assert [a.first[0] for a in hal.sent] == [0.1]
    assert runner.recent_ticks[-1].withheld_reason == "estop"


def test_estop_from_the_skill_is_not_an_ordinary_failure() -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, raise_on={1: ROSEStopRequested("skill saw a person")})
    runner, hal, _ = build(clock, skill=skill)
    runner.activate()
    result = runner.run(10)
    assert result.stop_reason == "estop"
    assert hal.estop_calls == 1
    assert result.failed_ticks == 0


def test_reader_failing_in_activate_rolls_back() -> None:
    clock = FakeClock()
    first = ScriptedReader("a", clock)
    second = ScriptedReader("b", clock, fail_open=ROSHardwareError("camera b unplugged"))
    third = ScriptedReader("c", clock)
    configs = [SensorReaderConfig(sensor_id=s) for s in "abc"]
    runner, hal, _ = build(clock, readers=[first, second, third], sensor_configs=configs)
    with pytest.raises(ROSHardwareError, match="unplugged"):
        runner.activate()
    assert not hal.is_connected
    assert hal.disconnect_calls == 1
    assert first.close_calls == 1
    assert not first.is_open
    assert third.open_calls == 0
    assert not runner.is_active


def test_hal_connect_failure_opens_no_reader() -> None:
    clock = FakeClock()
    reader = ScriptedReader("a", clock)
    hal = RecordingHAL(JOINTS, clock_ns=clock.now_ns, fail_connect=ROSHardwareError("no bus"))
    runner, _, _ = build(clock, readers=[reader], sensor_configs=[SensorReaderConfig(sensor_id="a")], hal=hal)
    with pytest.raises(ROSHardwareError):
        runner.activate()
    assert reader.open_calls == 0


def test_deactivate_closes_everything_even_if_one_close_fails() -> None:
    clock = FakeClock()
    reader = ScriptedReader("a", clock)

    def broken_close() -> None:
        raise ROSHardwareError("close failed")

    other = ScriptedReader("b", clock)
    other.close = broken_close  # type: ignore[method-assign]
    configs = [SensorReaderConfig(sensor_id="a"), SensorReaderConfig(sensor_id="b")]
    runner, hal, _ = build(clock, readers=[reader, other], sensor_configs=configs)
    runner.activate()
    runner.deactivate()
    assert not reader.is_open
    assert not hal.is_connected
    runner.deactivate()  # idempotent
    assert hal.disconnect_calls == 1


def _stale_after_first_read(cam: ScriptedReader, age_ms: float) -> None:
    """The start-up check sees one fresh frame; every read after it finds one ``age_ms`` old."""
    ages = iter([cam.age_ms])
    cam.on_read = lambda: setattr(cam, "age_ms", next(ages, age_ms))


def test_stale_required_sensor_withholds_the_action() -> None:
    clock = FakeClock()
    cam = ScriptedReader("cam", clock, max_age_ms=100.0)
    _stale_after_first_read(cam, 500.0)
    runner, hal, skill = build(clock, readers=[cam], sensor_configs=[SensorReaderConfig(sensor_id="cam")])
    runner.activate()
    result = runner.run(2)
    assert hal.sent == []
    assert skill.seen == []  # no inference on a world state with a stale required sensor
    assert result.stale_reads == 2
    assert runner.recent_ticks[0].withheld_reason == "stale_sensor"
    assert runner.recent_ticks[0].stale_sensors == ["cam"]
    figures = result.metadata["sensors"]["cam"]
    assert (figures["reads"], figures["stale_reads"]) == (2, 2)
    assert (figures["stale_age_ms_max"], figures["max_age_ms"]) == (500.0, 100.0)


def test_a_required_sensor_never_fresh_fails_the_start_naming_it_and_its_frame_age() -> None:
    clock = FakeClock()
    cam = ScriptedReader("cam", clock, age_ms=500.0, max_age_ms=100.0)
    runner, hal, skill = build(clock, readers=[cam], sensor_configs=[SensorReaderConfig(sensor_id="cam")])
    runner.activate()
    with pytest.raises(
        ROSRuntimeError, match=r"sensor 'cam' delivered no frame younger than 100 ms \(its newest was 500"
    ):
        runner.run(2)
    assert hal.sent == []
    assert skill.seen == []
    assert not runner.recent_ticks


def test_the_first_tick_waits_until_a_slow_required_sensor_is_fresh() -> None:
    clock = FakeClock()
    cam = ScriptedReader("cam", clock, max_age_ms=100.0)
    ages = iter([400.0, 300.0, 200.0])  # a camera catching up after start: three stale reads, then fresh
    cam.on_read = lambda: setattr(cam, "age_ms", next(ages, 1.0))
    runner, hal, _skill = build(clock, readers=[cam], sensor_configs=[SensorReaderConfig(sensor_id="cam")])
    runner.activate()
    result = runner.run(3)
    assert result.stale_reads == 0
    assert result.withheld_actions == 0
    assert len(hal.sent) == 3
    assert result.metadata["sensors"]["cam"]["stale_reads"] == 0


def test_stale_optional_sensor_is_reported_and_tick_goes_on() -> None:
    clock = FakeClock()
    cam = ScriptedReader("cam", clock, age_ms=500.0, max_age_ms=100.0)
    config = SensorReaderConfig(sensor_id="cam", required=False)
    runner, hal, skill = build(clock, readers=[cam], sensor_configs=[config])
    runner.activate()
    result = runner.run(2)
    assert len(hal.sent) == 2
    assert result.stale_reads == 2
    diag = skill.seen[0].diagnostics["cam"]
    assert diag.stale
    assert not diag.required


def test_failed_read_state_withholds_and_is_counted() -> None:
    clock = FakeClock()
    hal = RecordingHAL(JOINTS, clock_ns=clock.now_ns, fail_read_on={1})
    skill = ScriptedSkill(JOINTS, actions=rows(0.1, 0.2, 0.3))
    runner, _, _ = build(clock, skill=skill, hal=hal)
    runner.activate()
    result = runner.run(3)
    assert runner.recent_ticks[1].withheld_reason == "read_state"
    assert result.failed_ticks == 1
    assert len(hal.sent) == 2


def test_skill_exception_withholds_then_stops_after_consecutive_failures() -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, raise_on={2: RuntimeError("CUDA out of memory")})
    runner, hal, _ = build(clock, skill=skill, max_consecutive_failures=3)
    runner.activate()
    result = runner.run(20)
    # The skill's error latch keeps every later step failing: ticks 2, 3, 4 fail, then the run stops.
    assert result.stop_reason == "faults"
    assert result.n_ticks == 5
    assert len(hal.sent) == 2
    assert {t.withheld_reason for t in list(runner.recent_ticks)[2:]} == {"skill_error"}


def test_drop_policy_never_sends_late_action_to_hal() -> None:
    clock = FakeClock()

    def slow_second_step(i: int) -> None:
        if i == 1:
            clock.advance(1.5 * PERIOD)

    skill = ScriptedSkill(JOINTS, actions=rows(0.1, 0.2, 0.3), on_step=slow_second_step)
    runner, hal, _ = build(clock, skill=skill, deadline_overrun_policy=DeadlineOverrunPolicy.DROP)
    runner.activate()
    result = runner.run(3)
    assert [a.first[0] for a in hal.sent] == [0.1, 0.3]
    assert result.dropped_actions == 1
    assert runner.recent_ticks[1].withheld_reason == "deadline"


def test_hal_send_failure_is_a_fault_not_a_crash() -> None:
    clock = FakeClock()
    hal = RecordingHAL(JOINTS, clock_ns=clock.now_ns, fail_send_on={0})
    runner, _, _ = build(clock, hal=hal)
    runner.activate()
    result = runner.run(3)
    assert runner.recent_ticks[0].withheld_reason == "hal_error"
    assert not runner.recent_ticks[0].action_applied
    assert result.failed_ticks == 1
    assert len(hal.sent) == 2


def test_transient_reader_error_clears_on_the_next_good_frame() -> None:
    clock = FakeClock()
    cam = ScriptedReader("cam", clock)
    runner, hal, skill = build(clock, readers=[cam], sensor_configs=[SensorReaderConfig(sensor_id="cam")])
    failed = []

    def fail_during_tick_one() -> None:
        if len(runner.recent_ticks) == 1 and not failed:
            failed.append(True)
            raise ROSHardwareError("USB reset")

    cam.on_read = fail_during_tick_one
    runner.activate()
    result = runner.run(4)
    reasons = [t.withheld_reason for t in runner.recent_ticks]
    assert reasons == [None, "stale_sensor", None, None]
    assert len(hal.sent) == 3
    assert result.failed_ticks == 1
    assert skill.seen[-1].diagnostics["cam"].healthy


def test_synced_cameras_within_skew_reach_the_skill() -> None:
    from openral_core import SyncConfig  # noqa: PLC0415

    clock = FakeClock()
    cams = [ScriptedReader("left", clock, age_ms=2.0), ScriptedReader("right", clock, age_ms=4.0)]
    configs = [SensorReaderConfig(sensor_id="left"), SensorReaderConfig(sensor_id="right")]
    sync = SyncConfig(sensors=["left", "right"], max_skew_ms=5.0, timeout_ms=10.0)
    runner, hal, skill = build(clock, readers=cams, sensor_configs=configs, sync=sync)
    runner.activate()
    runner.run(3)
    assert len(hal.sent) == 3
    frames = skill.seen[-1].image_frames
    assert frames is not None
    assert abs(frames["left"].stamp_ns - frames["right"].stamp_ns) <= 5_000_000


def test_failed_sync_withholds_when_a_synced_camera_is_required() -> None:
    from openral_core import SyncConfig  # noqa: PLC0415

    clock = FakeClock()
    # "right" always serves frames 60 ms old: never within 5 ms of "left".
    cams = [ScriptedReader("left", clock, age_ms=1.0), ScriptedReader("right", clock, age_ms=60.0)]
    configs = [SensorReaderConfig(sensor_id="left"), SensorReaderConfig(sensor_id="right")]
    sync = SyncConfig(sensors=["left", "right"], max_skew_ms=5.0, timeout_ms=10.0)
    runner, hal, skill = build(clock, readers=cams, sensor_configs=configs, sync=sync)
    runner.activate()
    result = runner.run(2)
    assert hal.sent == []
    assert skill.seen == []
    assert runner.recent_ticks[0].withheld_reason == "stale_sensor"
    assert sorted(runner.recent_ticks[0].stale_sensors) == ["left", "right"]
    assert result.stale_reads == 4


def test_episodes_reset_the_skill_and_record_outcomes() -> None:
    from openral_core import ROSRuntimeError  # noqa: PLC0415

    clock = FakeClock()
    runner, _, skill = build(clock)
    runner.activate()
    assert runner.episode_start("pick the cube") == 0
    with pytest.raises(ROSRuntimeError, match="still open"):
        runner.episode_start("again")
    runner.run(2)
    assert skill.seen[-1].task == "pick the cube"
    runner.episode_end(success=True)
    with pytest.raises(ROSRuntimeError, match="no episode"):
        runner.episode_end(success=False)
    assert runner.episode_start("place it") == 1
    assert skill.calls.count("reset") == 2
    runner.episode_end(success=False)
    assert [(e["task"], e["success"]) for e in runner.metadata["episodes"]] == [
        ("pick the cube", True),
        ("place it", False),
    ]


def test_observers_see_every_tick_and_a_failing_one_is_detached() -> None:
    clock = FakeClock()
    runner, hal, _ = build(clock)

    class Recorder:
        def __init__(self) -> None:
            self.ticks: list[tuple[int, bool]] = []
            self.closed = 0

        def on_tick(self, tick, world) -> None:
            self.ticks.append((tick.tick_idx, world is not None and world.joint_state is not None))

        def close(self) -> None:
            self.closed += 1

    class Broken(Recorder):
        def on_tick(self, tick, world) -> None:
            raise RuntimeError("disk full")

    good, broken = Recorder(), Broken()
    runner.observers.extend([broken, good])
    runner.activate()
    result = runner.run(3)
    assert result.n_ticks == 3
    assert len(hal.sent) == 3
    assert good.ticks == [(0, True), (1, True), (2, True)]
    assert broken not in runner.observers
    runner.deactivate()
    assert good.closed == 1


def test_background_threads_keep_ordinary_scheduling_under_realtime_knobs() -> None:
    import os  # noqa: PLC0415
    import threading  # noqa: PLC0415

    from openral_core import RealtimeConfig  # noqa: PLC0415

    clock = FakeClock()
    runner, _, _ = build(clock, realtime=RealtimeConfig(sched_fifo_priority=5))
    runner.activate()
    try:
        if runner.metadata["realtime"]["sched_fifo_priority"] != "applied":
            pytest.skip("SCHED_FIFO not permitted here (needs root or CAP_SYS_NICE); CI runs as root")
        assert os.sched_getscheduler(0) == os.SCHED_FIFO
        workers = [t for t in threading.enumerate() if t.name == "openral-telemetry"]
        assert workers
        assert all(os.sched_getscheduler(t.native_id) == os.SCHED_OTHER for t in workers)
    finally:
        runner.deactivate()
    assert os.sched_getscheduler(0) != os.SCHED_FIFO


def test_schedule_starts_just_after_a_camera_frame() -> None:
    class GridCamera(ScriptedReader):
        """Captures exactly every 33.3 ms of fake time; serves the latest captured frame."""

        period_ns = 33_333_333

        def _latest_stamp(self) -> int:
            return self.clock.now_ns() // self.period_ns * self.period_ns

        def read_latest(self, max_age_ms: float | None = None):
            frame = super().read_latest(float("inf"))
            return frame.model_copy(update={"stamp_ns": self._latest_stamp()})

        def read_synced(self, deadline_ns: int, *, newer_than_ns: int = 0):
            self.clock.sleep_until((newer_than_ns // self.period_ns + 1) * self.period_ns / 1e9)
            return self.read_latest()

    clock = FakeClock(start_s=100.0)
    clock.advance(0.020)  # the run starts 20 ms into a camera period
    cam = GridCamera("cam", clock)
    runner, _, skill = build(clock, readers=[cam], sensor_configs=[SensorReaderConfig(sensor_id="cam")])
    runner.activate()
    runner.run(3)
    for world in skill.seen:
        assert world.image_frames is not None
        age_ms = (world.stamp_ns - world.image_frames["cam"].stamp_ns) / 1e6
        assert 0 <= age_ms <= 3.0  # read ~2 ms after its capture, not most of a period later


def test_stop_requested_while_a_reader_opens_rolls_back_to_disconnected() -> None:
    """A stop signal arriving during start-up (after the HAL connected) unwinds the same rollback."""
    clock = FakeClock()
    readers = [ScriptedReader(s, clock) for s in "abc"]
    configs = [SensorReaderConfig(sensor_id=s) for s in "abc"]
    runner, hal, _ = build(clock, readers=readers, sensor_configs=configs)
    original_open = readers[1].open

    def open_then_signal() -> None:
        original_open()
        runner.request_stop("signal:SIGTERM")  # what the signal watcher does, from another thread

    readers[1].open = open_then_signal  # type: ignore[method-assign]
    with pytest.raises(ROSStopRequested) as info:
        runner.activate()
    assert info.value.reason == "signal:SIGTERM"
    assert hal.disconnect_calls == 1
    assert not hal.is_connected
    assert [r.close_calls for r in readers] == [1, 1, 0]
    assert readers[2].open_calls == 0
    assert not runner.is_active


def test_stop_requested_before_activate_connects_nothing() -> None:
    clock = FakeClock()
    runner, hal, _ = build(clock)
    runner.request_stop("signal:SIGINT")
    with pytest.raises(ROSStopRequested):
        runner.activate()
    assert hal.calls == []
    runner.deactivate()  # clears the request: the runner can start again
    runner.activate()
    assert runner.run(2).n_ticks == 2


class OutputSkill(ScriptedSkill):
    """Returns ``outputs[i]`` from step ``i`` whatever it is: the malformed results of a buggy skill."""

    def __init__(self, outputs: list[object]) -> None:
        super().__init__(JOINTS)
        self.outputs = outputs

    def _step_impl(self, world_state):  # type: ignore[override]
        index = self.steps_taken
        super()._step_impl(world_state)
        return self.outputs[index] if index < len(self.outputs) else self.hold_action


def _malformed() -> list[object]:
    good = Action(joint_names=JOINTS, targets=[[0.1, 0.0, 0.0]])
    return [
        {"joint_names": JOINTS, "targets": [[0.1, 0.0, 0.0]]},
        None,
        Action.model_construct(joint_names=JOINTS, targets=np.zeros((1, 3))),
        Action.model_construct(joint_names=JOINTS, targets=[np.zeros(3)]),
        Action.model_construct(joint_names=JOINTS, targets=[[None, 0.0, 0.0]]),
        Action.model_construct(joint_names=JOINTS, targets=[]),
        Action.model_construct(joint_names=JOINTS, targets=[[0.1, 0.0]]),
        Action.model_construct(joint_names=JOINTS, targets=[[True, 0.0, 0.0]]),
        Action.model_construct(joint_names=[], targets=[[]]),
        Action.model_construct(joint_names=JOINTS, targets=[["0.1", 0.0, 0.0]], control_mode="teleport"),
        good,
    ]


def test_malformed_skill_output_is_withheld_as_a_typed_skill_fault() -> None:
    clock = FakeClock()
    outputs = _malformed()
    runner, hal, _ = build(clock, skill=OutputSkill(outputs), safety=RejectingSafety(), max_consecutive_failures=100)
    runner.activate()
    result = runner.run(len(outputs))
    assert result.n_ticks == len(outputs), "the run survives every malformed output"
    bad = list(runner.recent_ticks)[:-1]
    assert {t.withheld_reason for t in bad} == {WithheldReason.INVALID_ACTION}
    assert all(t.requested_action is None and not t.action_applied for t in bad)
    assert result.failed_ticks == len(bad), "each counts as a failed tick"
    assert [a.first for a in hal.sent] == [[0.1, 0.0, 0.0]], "only the valid action reached the robot"
    assert runner.recent_ticks[-1].action_applied


def test_consecutive_malformed_outputs_stop_the_run_safely() -> None:
    clock = FakeClock()
    runner, hal, _ = build(clock, skill=OutputSkill([None] * 10), max_consecutive_failures=3)
    runner.activate()
    result = runner.run(10)
    assert result.stop_reason == "faults"
    assert result.n_ticks == 3
    assert hal.sent == []


def test_invalid_action_is_traced_on_the_inference_span(telemetry) -> None:
    clock = FakeClock()
    runner, _, _ = build(clock, skill=OutputSkill([{"not": "an action"}]))
    runner.activate()
    runner.run(1)
    runner.deactivate()
    runner.flush_telemetry()
    (span,) = telemetry.spans("skill.chunk_inference")
    assert [e.name for e in span.events] == ["openral.event.invalid_action"]
    assert "dict, not an Action" in span.events[0].attributes["exception.message"]


def test_a_tick_prepared_before_its_slot_is_traced_from_the_slot(telemetry) -> None:
    """Ticks are prepared in the idle time before their slot; their span still starts when the slot does."""
    runner, _, _ = build(SystemClock())
    runner.activate()
    runner.run(4)
    runner.deactivate()
    runner.flush_telemetry()
    spans = sorted(telemetry.spans("rskill.tick"), key=lambda s: s.start_time)
    assert len(spans) == 4
    for span, tick in zip(spans, runner.recent_ticks, strict=True):
        span_ms = (span.end_time - span.start_time) / 1e6
        # Without the restart the span of each later tick would also cover the ~33 ms wait for its slot.
        assert span_ms - tick.tick_ms < PERIOD * 1e3 / 2
    gaps = [(b.start_time - a.end_time) / 1e6 for a, b in itertools.pairwise(spans)]
    assert min(gaps) > PERIOD * 1e3 / 2


class SeedProtocolReader:
    """A third-party reader written to the five members of the SensorReader protocol, nothing more.

    Frames are captured in real time on a thread, stamped on the monotonic clock.
    """

    def __init__(self, sensor_id: str, period_s: float = 0.005) -> None:
        import threading  # noqa: PLC0415

        self.sensor_id = sensor_id
        self._period_s = period_s
        self._frame = None
        self._seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._capture, daemon=True)
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        self._open = True
        self._thread.start()

    def close(self) -> None:
        self._open = False
        self._stop.set()
        self._thread.join(2)

    def _capture(self) -> None:
        import time  # noqa: PLC0415

        from openral_core import FrameEncoding, SensorFrame  # noqa: PLC0415

        while not self._stop.wait(self._period_s):
            self._seq += 1
            self._frame = SensorFrame(
                sensor_id=self.sensor_id,
                stamp_ns=time.monotonic_ns(),
                width=2,
                height=2,
                encoding=FrameEncoding.BGR8,
                seq=self._seq,
                data=bytes(12),
            )

    def read_latest(self, max_age_ms: float | None = None):
        from openral_core import ROSPerceptionStale  # noqa: PLC0415

        if self._frame is None:
            raise ROSPerceptionStale(self.sensor_id, age_ms=None, max_age_ms=max_age_ms)
        return self._frame


def test_a_reader_with_only_the_seed_protocol_runs_and_syncs() -> None:
    from openral_core import SyncConfig  # noqa: PLC0415
    from openral_runner.clock import SystemClock  # noqa: PLC0415
    from openral_runner.sensor_reader import SyncedSensorReader  # noqa: PLC0415

    readers = [SeedProtocolReader("left"), SeedProtocolReader("right"), SeedProtocolReader("wrist")]
    assert not isinstance(readers[0], SyncedSensorReader)
    configs = [SensorReaderConfig(sensor_id=r.sensor_id, max_age_ms=500) for r in readers]
    sync = SyncConfig(sensors=["left", "right"], max_skew_ms=20.0, timeout_ms=30.0)
    skill = ScriptedSkill(JOINTS)
    skill.configure()
    skill.activate()
    runner = HardwareRunner(
        hal=RecordingHAL(JOINTS),
        skill=skill,
        aggregator=WorldStateAggregator(joint_max_age_ms=1000.0, sensors=configs),
        sensor_readers=readers,
        sync=sync,
        rate_hz=100.0,
        clock=SystemClock(),
    )
    runner.activate()
    try:
        result = runner.run(20)
    finally:
        runner.deactivate()
    assert result.n_ticks == 20
    assert result.withheld_actions <= 2, [t.withheld_reason for t in runner.recent_ticks]
    frames = skill.seen[-1].image_frames
    assert frames is not None
    assert set(frames) == {"left", "right", "wrist"}
    assert abs(frames["left"].stamp_ns - frames["right"].stamp_ns) <= 20e6


def _thumbnails(runner: HardwareRunner) -> list[ThumbnailPublisher]:
    return [o for o in runner.observers if isinstance(o, ThumbnailPublisher)]


def test_thumbnails_follow_the_seed_keyword_as_one_more_observer() -> None:
    clock = FakeClock()
    cam = ScriptedReader("front", clock)
    configs = [SensorReaderConfig(sensor_id="front")]
    watching = EpisodeLog()
    runner, _, _ = build(clock, readers=[cam], sensor_configs=configs, thumbnail_hz=25.0, observers=[watching])
    assert runner.observers[0] is watching, "the shorthand's publisher comes after the observers given"
    assert [t.rate_hz for t in _thumbnails(runner)] == [25.0]
    assert _thumbnails(build(clock, readers=[cam], sensor_configs=configs, thumbnail_hz=0.0)[0]) == []
    assert _thumbnails(build(clock, thumbnail_hz=25.0)[0]) == [], "no camera, no thumbnails"
    with pytest.raises(ROSConfigError, match="thumbnail_hz"):
        build(clock, readers=[cam], sensor_configs=configs, thumbnail_hz=float("nan"))


def test_the_seed_default_is_25_hz_without_observers_and_none_with_them() -> None:
    clock = FakeClock()
    configs = [SensorReaderConfig(sensor_id="front")]
    as_the_spec_builds_it = build(
        clock, readers=[ScriptedReader("front", clock)], sensor_configs=configs, thumbnail_hz=None
    )
    assert [t.rate_hz for t in _thumbnails(as_the_spec_builds_it[0])] == [25.0]
    composed = build(
        clock, readers=[ScriptedReader("front", clock)], sensor_configs=configs, thumbnail_hz=None, observers=[]
    )
    assert _thumbnails(composed[0]) == [], "a runner given its observers has exactly those"


def test_a_skill_that_finishes_its_task_ends_the_run_cleanly() -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, actions=rows(0.1, 0.2), raise_on={2: ROSStopRequested("cube placed")})
    runner, hal, _ = build(clock, skill=skill, max_consecutive_failures=1)
    runner.activate()
    result = runner.run(10)
    assert result.stop_reason == StopReason.SKILL_DONE
    assert result.n_ticks == 3
    assert result.failed_ticks == 0
    assert runner.recent_ticks[-1].withheld_reason == WithheldReason.SKILL_DONE
    assert len(hal.sent) == 2
    assert skill.last_error is None, "a finished task does not latch the skill's error"


class EpisodeLog(TickObserver):
    def __init__(self) -> None:
        self.events: list[tuple[object, ...]] = []
        self.closed = 0

    def on_tick(self, tick, world) -> None:
        self.events.append(("tick", tick.tick_idx, tick.episode_idx, tick.step_idx))

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        self.events.append(("start", episode_idx, task))

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        self.events.append(("end", episode_idx, success, keep))

    def close(self) -> None:
        self.closed += 1


def test_the_recorder_hears_episodes_first_and_ticks_carry_their_episode_and_step() -> None:
    clock = FakeClock()
    recorder = EpisodeLog()
    other = EpisodeLog()
    runner, _, _ = build(clock, recorder=recorder, observers=[other])
    assert runner.observers == [recorder, other], "the recorder shorthand is the first observer"
    runner.activate()
    runner.run(1)
    runner.episode_start("pick")
    runner.run(2)
    runner.episode_end(success=True)
    runner.episode_start("place")
    runner.run(1)
    runner.episode_end(success=False, keep=False)
    runner.deactivate()
    assert recorder.events == [
        ("tick", 0, None, None),
        ("start", 0, "pick"),
        ("tick", 1, 0, 0),
        ("tick", 2, 0, 1),
        ("end", 0, True, True),
        ("start", 1, "place"),
        ("tick", 3, 1, 0),
        ("end", 1, False, False),
    ]
    assert other.events == recorder.events
    assert recorder.closed == 1


def test_an_observer_failing_at_an_episode_boundary_is_detached_and_the_run_goes_on() -> None:
    class Broken(EpisodeLog):
        def on_episode_start(self, episode_idx: int, task: str) -> None:
            raise RuntimeError("disk full")

    clock = FakeClock()
    runner, hal, _ = build(clock)
    broken = Broken()
    runner.observers.append(broken)
    runner.activate()
    runner.episode_start("pick")
    result = runner.run(3)
    runner.deactivate()
    assert broken not in runner.observers
    assert result.n_ticks == 3
    assert len(hal.sent) == 3


class ThumbnailViewer(TickObserver):
    """A viewer that takes thumbnails (a ``ThumbnailSubscriber``), as the Foxglove view does."""

    def __init__(self) -> None:
        self.thumbs: list[object] = []
        self.arrived = threading.Event()

    def on_tick(self, tick, world) -> None:
        return

    def on_thumbnail(self, thumb) -> None:
        self.thumbs.append(thumb)
        self.arrived.set()

    def close(self) -> None:
        return


def test_a_thumbnails_observer_entry_feeds_every_viewer_without_runner_special_cases() -> None:
    clock = FakeClock()
    cam = ScriptedReader("front", clock, width=8, height=6)
    publisher = ThumbnailPublisher.from_config({"rate_hz": 1000.0, "quality": 50}, CONTEXT)
    viewer = ThumbnailViewer()
    runner, _, _ = build(clock, readers=[cam], sensor_configs=[SensorReaderConfig(sensor_id="front")])
    assert _thumbnails(runner) == []
    runner.observers.extend([publisher, viewer])
    runner.activate()
    try:
        runner.run(1)
        assert viewer.arrived.wait(10), "the viewer was subscribed to the thumbnails observer at activation"
    finally:
        runner.deactivate()
    assert viewer.thumbs[0].sensor_id == "front"  # type: ignore[attr-defined]
    with pytest.raises(ROSConfigError, match="rate"):
        ThumbnailPublisher.from_config({"rate": 5}, CONTEXT)


class RefusingObserver(TickObserver):
    """An observer whose start refuses (a dataset folder it may not use, a port taken)."""

    def __init__(self) -> None:
        self.closed = 0

    def on_tick(self, tick, world) -> None:
        return

    def start(self) -> None:
        raise ROSConfigError("the folder holds other files", field="--dataset-out")

    def close(self) -> None:
        self.closed += 1


def test_an_observer_that_cannot_start_is_refused_before_the_robot_is_touched() -> None:
    clock = FakeClock()
    cam = ScriptedReader("front", clock)
    refusing, watching = RefusingObserver(), EpisodeLog()
    runner, hal, _ = build(clock, readers=[cam], sensor_configs=[SensorReaderConfig(sensor_id="front")])
    runner.observers.extend([watching, refusing])
    with pytest.raises(ROSConfigError, match="other files"):
        runner.activate()
    assert hal.connect_calls == 0
    assert not cam.is_open
    assert refusing.closed == 1
    assert watching.closed == 1, "what was built is closed by the rollback"


def test_each_run_reports_its_own_sensor_reads() -> None:
    clock = FakeClock()
    cam = ScriptedReader("cam", clock, max_age_ms=100.0)
    _stale_after_first_read(cam, 500.0)
    runner, _hal, _skill = build(clock, readers=[cam], sensor_configs=[SensorReaderConfig(sensor_id="cam")])
    runner.activate()
    first = runner.run(2)
    cam.age_ms = 1.0
    cam.on_read = None
    second = runner.run(3)
    assert first.metadata["sensors"]["cam"]["stale_reads"] == 2
    assert (second.metadata["sensors"]["cam"]["reads"], second.metadata["sensors"]["cam"]["stale_reads"]) == (3, 0)
    assert second.metadata["sensors"]["cam"]["stale_age_ms_max"] is None
