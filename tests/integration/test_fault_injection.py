"""Fault injection: one test per fault row of the README's reliability table.

Each test asserts the outcome the runner promises and that nothing unsafe reached the robot:
every command the servos (or the recording HAL) received lies inside the joint limits, and no
command arrives after a fault that should have stopped the loop. The serial rows drive the
real SO-101 HAL over the Feetech protocol against the servo-bus emulator on a pseudo-terminal.
"""

from __future__ import annotations

import json
import math
import signal
import threading
from pathlib import Path

import pytest

from openral_core import (
    Action,
    DeadlineOverrunPolicy,
    ROSEStopRequested,
    ROSHardwareError,
    SafetyConfig,
    SafetyMode,
    SensorReaderConfig,
)
from openral_hal.manifests import load_robot_manifest
from openral_hal.testing import RecordingHAL
from openral_rskill.testing import ScriptedSkill
from openral_runner.envelope import EnvelopeSafetyClient
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import FakeClock, ScriptedReader
from openral_world_state import WorldStateAggregator

pytest.importorskip("serial", reason="needs the 'serial' extra (pyserial) for the servo-bus rows")

from openral_hal.feetech import protocol as p
from openral_hal.feetech.calibration import ArmCalibration, save_calibration
from openral_hal.feetech.emulator import ServoBusEmulator
from openral_hal.feetech.hal import SO10xFollowerHAL
from openral_hal.feetech.protocol import Instruction, Register
from openral_runner.safety import SafetyClient

ROBOT = load_robot_manifest("so101_follower")
NAMES = ROBOT.joint_names
RATE = 30.0
IDS = [j.servo_id for j in ROBOT.joints]


def inside_limits(positions: list[float]) -> bool:
    return all(
        math.isfinite(v) and spec.lower - 1e-9 <= v <= spec.upper + 1e-9
        for v, spec in zip(positions, ROBOT.joints, strict=True)
    )


def serial_hal(bus: ServoBusEmulator, tmp_path: Path, **params: object) -> SO10xFollowerHAL:
    calibration = tmp_path / "so101.json"
    save_calibration(ArmCalibration.from_manifest(ROBOT), calibration)
    return SO10xFollowerHAL(
        ROBOT, {"port": bus.port, "calibration": str(calibration), "timeout_s": 0.02, "retries": 2, **params}
    )


def bus_caught_up(hal: SO10xFollowerHAL) -> None:
    """Return once the emulator has applied every packet the HAL wrote before now.

    Writes get no reply to wait for; a read does, and the emulator answers the line in order, so
    the read's reply comes after everything written before it.
    """
    hal.read_state()


def first_tick(bus: ServoBusEmulator) -> threading.Event:
    """Set once the runner writes a goal after start-up turned torque on: that goal is a tick's command."""
    torque_on = threading.Event()
    ticking = threading.Event()

    def on_request(packet: p.Packet) -> None:
        if packet.code != Instruction.SYNC_WRITE:
            return
        if packet.params[0] == Register.TORQUE_ENABLE and packet.params[3] == 1:
            torque_on.set()
        elif packet.params[0] == Register.GOAL_POSITION and torque_on.is_set():
            ticking.set()

    bus.on_request = on_request
    return ticking


def runner_for(
    hal: object, skill: ScriptedSkill, *, clock: FakeClock | None = None, **kwargs: object
) -> HardwareRunner:
    skill.configure()
    skill.activate()
    aggregator_kwargs: dict[str, object] = {"joint_max_age_ms": 200.0, "sensors": kwargs.pop("sensor_configs", [])}
    if clock is not None:
        aggregator_kwargs["clock"] = clock.now_ns
    return HardwareRunner(
        hal=hal,  # type: ignore[arg-type]
        skill=skill,
        aggregator=WorldStateAggregator(**aggregator_kwargs),  # type: ignore[arg-type]
        safety_client=kwargs.pop("safety", EnvelopeSafetyClient(ROBOT, rate_hz=RATE)),  # type: ignore[arg-type]
        rate_hz=RATE,
        clock=clock,
        **kwargs,  # type: ignore[arg-type]
    )


def goals_in_radians(bus: ServoBusEmulator) -> list[float]:
    calibration = ArmCalibration.from_manifest(ROBOT)
    goals = bus.goals()
    return [
        calibration.joints[name].to_radians(goals[spec.servo_id])
        for name, spec in zip(NAMES, ROBOT.joints, strict=True)
    ]


# -- servo bus -------------------------------------------------------------------------------------


def test_servo_timeout_is_retried_and_the_tick_goes_on(tmp_path: Path) -> None:
    with ServoBusEmulator(IDS) as bus:
        hal = serial_hal(bus, tmp_path)
        runner = runner_for(hal, ScriptedSkill(NAMES, hold=[0.0] * 6))
        runner.activate()
        try:
            bus_caught_up(hal)  # the writes of connect() get no reply: they must not take the dropped replies
            bus.drop_replies = 2  # two lost replies: within the bus's retry budget
            result = runner.run(10)
            timeouts = hal._bus().stats.timeouts
        finally:
            runner.deactivate()
        assert timeouts >= 2
        assert result.failed_ticks == 0
        assert result.withheld_actions == 0
        assert inside_limits(goals_in_radians(bus))


def test_corrupt_packet_is_detected_and_retried(tmp_path: Path) -> None:
    with ServoBusEmulator(IDS) as bus:
        hal = serial_hal(bus, tmp_path)
        runner = runner_for(hal, ScriptedSkill(NAMES, hold=[0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))
        runner.activate()
        try:
            bus.corrupt_checksum = 1
            result = runner.run(10)
            stats = hal._bus().stats
            bad_packets, retries = stats.bad_packets, stats.retries
        finally:
            runner.deactivate()
        assert bad_packets >= 1
        assert retries >= 1
        assert result.failed_ticks == 0
        assert inside_limits(goals_in_radians(bus))


def test_missing_servo_at_connect_is_named_and_nothing_moves(tmp_path: Path) -> None:
    with ServoBusEmulator(IDS) as bus:
        bus.missing_ids = {4}
        hal = serial_hal(bus, tmp_path)
        reader = ScriptedReader("cam", FakeClock())
        runner = runner_for(
            hal, ScriptedSkill(NAMES), sensor_readers=[reader], sensor_configs=[SensorReaderConfig(sensor_id="cam")]
        )
        goals_before = bus.goals()
        with pytest.raises(ROSHardwareError, match="4"):
            runner.activate()
        assert not hal.is_connected
        assert reader.open_calls == 0  # the HAL is opened first; nothing after it was started
        assert bus.goals() == goals_before
        assert not any(bus.torque().values())


def test_bus_gone_mid_run_withholds_then_stops_safely(tmp_path: Path) -> None:
    with ServoBusEmulator(IDS) as bus:
        hal = serial_hal(bus, tmp_path)
        runner = runner_for(hal, ScriptedSkill(NAMES, hold=[0.0] * 6), max_consecutive_failures=3)
        runner.activate()
        try:
            runner.run(5)
            bus_caught_up(hal)
            goals_before = bus.goals()
            bus.disconnect()
            result = runner.run(50)
        finally:
            runner.deactivate()
        assert result.stop_reason == "faults"
        assert result.n_ticks == 3
        assert {t.withheld_reason for t in runner.recent_ticks} == {"read_state"}
        assert not any(t.action_applied for t in runner.recent_ticks)
        assert bus.goals() == goals_before  # no command reached the (gone) bus


# -- skill, sensors, safety ------------------------------------------------------------------------


def test_skill_raising_withholds_and_stops_after_consecutive_failures() -> None:
    clock = FakeClock()
    hal = RecordingHAL(ROBOT, clock_ns=clock.now_ns)
    skill = ScriptedSkill(NAMES, raise_on={3: RuntimeError("policy crashed")})
    runner = runner_for(hal, skill, clock=clock, max_consecutive_failures=4)
    runner.activate()
    result = runner.run(100)
    assert result.stop_reason == "faults"
    assert len(hal.sent) == 3
    assert all(inside_limits(a.first) for a in hal.sent)


def test_skill_too_slow_under_drop_never_sends_the_late_action() -> None:
    clock = FakeClock()
    hal = RecordingHAL(ROBOT, clock_ns=clock.now_ns)

    def slow(step: int) -> None:
        if step == 2:
            clock.advance(2.5 / RATE)

    skill = ScriptedSkill(NAMES, actions=[[0.01 * i] + [0.0] * 5 for i in range(6)], on_step=slow)
    runner = runner_for(hal, skill, clock=clock, deadline_overrun_policy=DeadlineOverrunPolicy.DROP)
    runner.activate()
    result = runner.run(6)
    assert result.dropped_actions == 1
    assert 0.02 not in [round(a.first[0], 6) for a in hal.sent]
    assert result.missed_slots == 2


def test_stale_required_sensor_withholds_every_affected_tick() -> None:
    clock = FakeClock()
    hal = RecordingHAL(ROBOT, clock_ns=clock.now_ns)
    cam = ScriptedReader("cam", clock, age_ms=1.0, max_age_ms=100.0)
    runner = runner_for(
        hal,
        ScriptedSkill(NAMES),
        clock=clock,
        sensor_readers=[cam],
        sensor_configs=[SensorReaderConfig(sensor_id="cam")],
    )
    runner.activate()
    runner.run(3)
    # The camera freezes once the next run has started on a fresh frame (a run never starts on a stale one).
    ages = iter([1.0])
    cam.on_read = lambda: setattr(cam, "age_ms", next(ages, 400.0))
    result = runner.run(3)
    assert result.withheld_actions == 3
    assert {t.withheld_reason for t in runner.recent_ticks} == {"stale_sensor"}
    assert len(hal.sent) == 3  # only the three fresh ticks acted


@pytest.mark.parametrize("mode", list(SafetyMode))
def test_safety_violation_never_reaches_the_hal(mode: SafetyMode) -> None:
    clock = FakeClock()
    hal = RecordingHAL(ROBOT, clock_ns=clock.now_ns)
    wild = [[5.0, -9.0, math.nan, 0.0, 0.0, 0.0], [0.0, 4.0, 0.0, 0.0, 0.0, 9.0], [math.inf] * 6]
    safety = EnvelopeSafetyClient.from_config(SafetyConfig(mode=mode), robot=ROBOT, rate_hz=RATE)
    runner = runner_for(hal, ScriptedSkill(NAMES, actions=wild), clock=clock, safety=safety)
    runner.activate()
    result = runner.run(3)
    assert result.safety_violations >= (1 if mode is SafetyMode.CLAMP else 3)
    assert all(inside_limits(a.first) for a in hal.sent)


def test_estop_stops_the_loop_and_holds_the_arm(tmp_path: Path) -> None:
    class EStopAfter(SafetyClient):
        envelope = EnvelopeSafetyClient(ROBOT, rate_hz=RATE).envelope

        def __init__(self) -> None:
            self.calls = 0

        def check_action(self, action: Action) -> Action | None:
            self.calls += 1
            if self.calls == 6:
                raise ROSEStopRequested("operator pressed stop")
            return None

    with ServoBusEmulator(IDS) as bus:
        hal = serial_hal(bus, tmp_path)
        skill = ScriptedSkill(NAMES, hold=[0.4, 0.0, 0.0, 0.0, 0.0, 0.0])
        runner = runner_for(hal, skill, safety=EStopAfter())
        runner.activate()
        try:
            result = runner.run(50)
            bus_caught_up(hal)  # the hold written at the e-stop has been applied
            goals, positions = bus.goals(), bus.positions()
        finally:
            runner.deactivate()
        assert result.stop_reason == "estop"
        assert result.n_ticks == 6
        # Held: every goal is where the servo stood at the e-stop, not the 0.4 rad target.
        assert all(abs(goals[i] - positions[i]) <= 40 for i in IDS)


def test_sigint_and_sigterm_finish_the_tick_and_exit_130_143(tmp_path: Path, deploy_process) -> None:
    calibration = tmp_path / "so101.json"
    save_calibration(ArmCalibration.from_manifest(ROBOT), calibration)
    deployment = tmp_path / "robot.yaml"
    for sig, code in ((signal.SIGINT, 130), (signal.SIGTERM, 143)):
        with ServoBusEmulator(IDS) as bus:
            deployment.write_text(
                "hal: {robot_id: so101_follower, adapter: so10x_follower, "
                f"params: {{port: {bus.port}, calibration: {calibration}}}}}\nvla: {{id: hello}}\n"
            )
            ticking = first_tick(bus)
            proc = deploy_process(["deploy", "--config", str(deployment), "--json"])
            assert ticking.wait(60), proc.stderr
            proc.proc.send_signal(sig)  # the process alone, in the middle of a run
            returncode, stdout = proc.finish(timeout=30)
            assert returncode == code, proc.stderr
            result = json.loads(stdout)
            assert result["stop_reason"] == f"signal:{sig.name}"
            assert result["n_ticks"] > 0


def test_reader_failing_at_activate_leaves_the_arm_disconnected(tmp_path: Path) -> None:
    with ServoBusEmulator(IDS) as bus:
        hal = serial_hal(bus, tmp_path)
        good = ScriptedReader("wrist", FakeClock())
        bad = ScriptedReader("front", FakeClock(), fail_open=ROSHardwareError("camera front unplugged"))
        configs = [SensorReaderConfig(sensor_id="wrist"), SensorReaderConfig(sensor_id="front")]
        runner = runner_for(hal, ScriptedSkill(NAMES), sensor_readers=[good, bad], sensor_configs=configs)
        with pytest.raises(ROSHardwareError, match="unplugged"):
            runner.activate()
        assert not hal.is_connected
        assert good.close_calls == 1
        assert not any(bus.torque().values())
