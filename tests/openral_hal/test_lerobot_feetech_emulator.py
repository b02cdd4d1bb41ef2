"""LeRobot's own Feetech driver, SO-101 follower and leader run against the emulated STS3215 bus.

Needs the ``lerobot`` extra (Python 3.12 or newer) and its Feetech SDK. Every robot connects with
``calibrate=False``: LeRobot's ``calibrate()`` asks the operator with ``input()``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.usefixtures("quick_thread_switches")

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

pytest.importorskip("torch", reason=LEROBOT_REASON)
pytest.importorskip("lerobot", reason=LEROBOT_REASON)
pytest.importorskip("scservo_sdk", reason=LEROBOT_REASON)

from lerobot.motors import Motor, MotorCalibration, MotorNormMode  # noqa: E402
from lerobot.motors.feetech import FeetechMotorsBus  # noqa: E402
from lerobot.robots.so_follower import SO101Follower, SO101FollowerConfig  # noqa: E402
from lerobot.teleoperators.so_leader import SO101Leader, SO101LeaderConfig  # noqa: E402

from openral_hal.feetech.emulator import ServoBusEmulator  # noqa: E402
from openral_hal.feetech.protocol import Register  # noqa: E402

JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
IDS = {name: i + 1 for i, name in enumerate(JOINTS)}
MAX_RES = 4095
# A calibrated arm: offsets from LeRobot's half-turn homing of a pose, ranges recorded around 2047.
CALIBRATION = {
    "shoulder_pan": (-1000, 1000, 3100),  # homing offset, range_min, range_max
    "shoulder_lift": (1500, 800, 3300),
    "elbow_flex": (-300, 900, 3000),
    "wrist_flex": (250, 850, 3200),
    "wrist_roll": (0, 0, 4095),
    "gripper": (700, 2000, 3500),
}
POSE = {1: 1047, 2: 3547, 3: 1747, 4: 2297, 5: 2047, 6: 2747}  # encoder ticks: present 2047 everywhere


def _calibration_file(folder: Path, device_id: str) -> Path:
    """Write LeRobot's calibration JSON: ``{motor: {id, drive_mode, homing_offset, range_min, range_max}}``."""
    data = {
        name: {"id": IDS[name], "drive_mode": 0, "homing_offset": off, "range_min": low, "range_max": high}
        for name, (off, low, high) in CALIBRATION.items()
    }
    path = folder / f"{device_id}.json"
    path.write_text(json.dumps(data))
    return path


def _calibrated_registers(phase: int | None = None) -> dict[int, dict[Register, int]]:
    """The EEPROM of servos that were calibrated earlier with :data:`CALIBRATION`."""
    out: dict[int, dict[Register, int]] = {}
    for name, (off, low, high) in CALIBRATION.items():
        registers = {Register.HOMING_OFFSET: off, Register.MIN_POSITION_LIMIT: low, Register.MAX_POSITION_LIMIT: high}
        if phase is not None:
            registers[Register.PHASE] = phase
        out[IDS[name]] = registers
    return out


def _degrees(name: str, present: int) -> float:
    """LeRobot's DEGREES normalisation of a present position: (ticks - mid) * 360 / 4095."""
    _, low, high = CALIBRATION[name]
    return (present - (low + high) / 2) * 360 / MAX_RES


def _goal_ticks(name: str, degrees: float) -> int:
    """LeRobot's inverse: int(degrees * 4095 / 360 + mid)."""
    _, low, high = CALIBRATION[name]
    return int(degrees * MAX_RES / 360 + (low + high) / 2)


def _gripper_percent(present: int) -> float:
    """LeRobot's RANGE_0_100 normalisation of the gripper."""
    _, low, high = CALIBRATION["gripper"]
    return (min(high, max(low, present)) - low) / (high - low) * 100


def _wait_for(condition: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


@pytest.fixture
def arm() -> Iterator[ServoBusEmulator]:
    """A calibrated SO-101 arm on the emulated bus, in the pose that reads 2047 on every joint."""
    with ServoBusEmulator(IDS.values(), initial_ticks=POSE, registers=_calibrated_registers()) as emu:
        yield emu


def _patient(bus: FeetechMotorsBus) -> FeetechMotorsBus:
    """Wait up to 0.5 s for each reply instead of LeRobot's 50 ms.

    A real servo answers within a millisecond from its own chip; the emulator's thread shares this
    process, and the machine, with the SDK's busy wait and other test runs, so it may be scheduled
    late. The requests and replies are unchanged.
    """
    handler = bus.port_handler

    def set_packet_timeout(packet_length: int) -> None:
        handler.packet_start_time = handler.getCurrentTime()
        handler.packet_timeout = handler.tx_time_per_byte * (packet_length + 3) + 500

    handler.setPacketTimeout = set_packet_timeout
    return bus


def _bus(port: str, calibration: dict[str, MotorCalibration] | None = None) -> FeetechMotorsBus:
    motors = {name: Motor(i, "sts3215", MotorNormMode.DEGREES) for name, i in IDS.items()}
    return _patient(FeetechMotorsBus(port=port, motors=motors, calibration=calibration))


def _follower(port: str, folder: Path) -> SO101Follower:
    _calibration_file(folder, "emulated_follower")
    robot = SO101Follower(SO101FollowerConfig(port=port, id="emulated_follower", calibration_dir=folder))
    _patient(robot.bus)
    return robot


# -- the motor bus --------------------------------------------------------------------------------


def test_the_handshake_finds_every_sts3215_and_one_firmware_version() -> None:
    with ServoBusEmulator(IDS.values()) as emu:
        bus = _bus(emu.port)
        bus.connect()  # pings every id, checks the model numbers and that the firmware versions agree
        try:
            assert bus._read_firmware_version(bus.ids) == dict.fromkeys(IDS.values(), "3.10")
            assert bus.broadcast_ping() == dict.fromkeys(IDS.values(), 777)
            assert bus.read("Max_Position_Limit", "gripper", normalize=False) == 4095
            assert bus.read("Lock", "gripper", normalize=False) == 0
        finally:
            bus.disconnect(disable_torque=False)


def test_the_handshake_names_a_servo_that_does_not_answer() -> None:
    with ServoBusEmulator(IDS.values()) as emu:
        emu.missing_ids = {4}
        bus = _bus(emu.port)
        with pytest.raises(RuntimeError, match=r"Missing motor IDs:\n  - 4"):
            bus.connect()
        bus.port_handler.closePort()


def test_a_written_calibration_is_read_back_and_makes_the_bus_calibrated() -> None:
    calibration = {
        name: MotorCalibration(id=IDS[name], drive_mode=0, homing_offset=off, range_min=low, range_max=high)
        for name, (off, low, high) in CALIBRATION.items()
    }
    with ServoBusEmulator(IDS.values()) as emu:
        bus = _bus(emu.port, calibration)
        bus.connect()
        try:
            assert not bus.is_calibrated  # factory servos: offset 0, limits 0..4095
            bus.disable_torque()
            bus.write_calibration(calibration)
            assert bus.is_calibrated
            assert bus.read_calibration() == calibration
            assert emu.servos[1].register(Register.HOMING_OFFSET) == -1000  # sign bit 11 decoded by the servo
            emu.power_cycle()  # written under Lock 0 (disable_torque): kept in EEPROM
            assert bus.read_calibration() == calibration
        finally:
            bus.disconnect()


def test_half_turn_homing_makes_the_present_pose_read_half_a_turn() -> None:
    encoders = {1: 3000, 2: 100, 3: 2047, 4: 4000, 5: 1200, 6: 2600}
    with ServoBusEmulator(IDS.values(), initial_ticks=encoders) as emu:
        bus = _bus(emu.port)
        bus.connect()
        try:
            bus.disable_torque()
            offsets = bus.set_half_turn_homings()
            assert offsets == {name: encoders[i] - 2047 for name, i in IDS.items()}
            assert bus.sync_read("Present_Position", normalize=False) == dict.fromkeys(JOINTS, 2047)
            emu.move_by_hand(2, 400)  # the shaft turns 300 ticks: the present position follows, offset kept
            assert bus.read("Present_Position", "shoulder_lift", normalize=False) == 2347
            assert emu.encoders()[2] == 400
        finally:
            bus.disconnect()


# -- the SO-101 follower ----------------------------------------------------------------------------


def test_the_follower_connects_calibrated_and_configures_the_servos(tmp_path: Path) -> None:
    with ServoBusEmulator(IDS.values(), initial_ticks=POSE, registers=_calibrated_registers(phase=0x1C)) as emu:
        robot = _follower(emu.port, tmp_path)
        robot.connect(calibrate=False)
        try:
            assert robot.is_calibrated
            servo = emu.servos[IDS["gripper"]]
            assert servo.register(Register.PHASE) == 0x0C  # LeRobot clears bit 4: single-turn feedback
            assert servo.register(Register.P_COEFFICIENT) == 16
            assert servo.register(Register.RETURN_DELAY) == 0
            assert servo.register(Register.MAXIMUM_ACCELERATION) == 254
            assert servo.register(Register.MAX_TORQUE_LIMIT) == 500
            assert servo.register(Register.PROTECTION_CURRENT) == 250
            assert servo.register(Register.OVERLOAD_TORQUE) == 25
            assert emu.torque() == dict.fromkeys(IDS.values(), True)
            assert servo.register(Register.LOCK) == 1  # enable_torque locks the EEPROM again
        finally:
            robot.disconnect()
        emu.power_cycle()  # configured under Lock 0: kept
        assert emu.servos[IDS["gripper"]].register(Register.MAX_TORQUE_LIMIT) == 500


def test_the_follower_reads_degrees_by_lerobots_formula_on_the_servo_ticks(tmp_path: Path) -> None:
    pose = {**POSE, 1: 1500, 3: 600, 6: 2800}
    with ServoBusEmulator(IDS.values(), initial_ticks=pose, registers=_calibrated_registers()) as emu:
        robot = _follower(emu.port, tmp_path)
        robot.connect(calibrate=False)
        try:
            present = emu.positions()
            assert present[1] == 2500  # encoder 1500 less offset -1000
            assert present[3] == 900  # encoder 600 less offset -300
            assert present[6] == 2100  # encoder 2800 less offset 700
            observation = robot.get_observation()
            for name in JOINTS[:-1]:
                assert observation[f"{name}.pos"] == pytest.approx(_degrees(name, present[IDS[name]]))
            assert observation["gripper.pos"] == pytest.approx(_gripper_percent(present[IDS["gripper"]]))
        finally:
            robot.disconnect()


def test_a_sent_action_is_reached_by_the_servos(arm: ServoBusEmulator, tmp_path: Path) -> None:
    robot = _follower(arm.port, tmp_path)
    robot.connect(calibrate=False)
    try:
        action = {"shoulder_pan.pos": 30.0, "shoulder_lift.pos": -25.0, "elbow_flex.pos": 40.0}
        robot.send_action(action)
        wanted = {IDS[k.removesuffix(".pos")]: _goal_ticks(k.removesuffix(".pos"), v) for k, v in action.items()}
        _wait_for(lambda: all(arm.positions()[i] == t for i, t in wanted.items()), "the goals to be reached")
        assert {i: arm.goals()[i] for i in wanted} == wanted
        observation = robot.get_observation()
        for key, degrees in action.items():
            assert observation[key] == pytest.approx(degrees, abs=360 / MAX_RES)
    finally:
        robot.disconnect()


def test_a_goal_beyond_the_calibrated_limit_stops_at_the_limit(arm: ServoBusEmulator, tmp_path: Path) -> None:
    robot = _follower(arm.port, tmp_path)
    robot.connect(calibrate=False)
    try:
        _, low, high = CALIBRATION["shoulder_pan"]
        robot.send_action({"shoulder_pan.pos": 170.0})  # degrees are not bounded by LeRobot: the servo clamps
        goal = _goal_ticks("shoulder_pan", 170.0)
        assert goal > high
        _wait_for(lambda: arm.goals()[1] == goal, "the goal to arrive")  # SYNC_WRITE gets no reply
        _wait_for(
            lambda: robot.bus.read("Moving", "shoulder_pan", normalize=False, num_retry=5) == 0, "the joint to stop"
        )
        assert arm.positions()[1] == high
        robot.send_action({"shoulder_pan.pos": -170.0})
        _wait_for(lambda: arm.positions()[1] == low, "the joint to reach its lower limit")
        assert robot.bus.read("Moving", "shoulder_pan", normalize=False, num_retry=5) == 0
    finally:
        robot.disconnect()


def test_disconnect_leaves_the_torque_off(arm: ServoBusEmulator, tmp_path: Path) -> None:
    robot = _follower(arm.port, tmp_path)
    robot.connect(calibrate=False)
    assert arm.torque() == dict.fromkeys(IDS.values(), True)
    robot.disconnect()
    assert arm.torque() == dict.fromkeys(IDS.values(), False)


# -- the SO-101 leader ------------------------------------------------------------------------------


def _leader_action(present: Mapping[int, int]) -> dict[str, float]:
    out = {f"{name}.pos": _degrees(name, present[IDS[name]]) for name in JOINTS[:-1]}
    out["gripper.pos"] = _gripper_percent(present[IDS["gripper"]])
    return out


def test_the_leader_follows_a_trajectory_played_on_its_servos(arm: ServoBusEmulator, tmp_path: Path) -> None:
    _calibration_file(tmp_path, "emulated_leader")
    leader = SO101Leader(SO101LeaderConfig(port=arm.port, id="emulated_leader", calibration_dir=tmp_path))
    _patient(leader.bus)
    leader.connect(calibrate=False)
    try:
        assert leader.is_calibrated
        assert arm.torque() == dict.fromkeys(IDS.values(), False)  # an operator moves a leader by hand
        start = dict(POSE)
        end = {i: t + (300 if i % 2 else -300) for i, t in POSE.items()}
        arm.play([(0.0, start)], loop=False)
        assert leader.get_action() == pytest.approx(_leader_action(dict.fromkeys(IDS.values(), 2047)))
        arm.play([(0.0, start), (0.5, end)], loop=False)
        seen: list[dict[str, Any]] = []

        def at_end() -> bool:
            seen.append(leader.get_action())
            return seen[-1] == pytest.approx(_leader_action({i: 2047 + end[i] - start[i] for i in IDS.values()}))

        _wait_for(at_end, "the leader to report the end of the trajectory")
        pan = [action["shoulder_pan.pos"] for action in seen]
        assert pan == sorted(pan)  # it followed the motion, it did not jump to the end
        assert len(set(pan)) > 2
    finally:
        leader.disconnect()


def test_motor_setup_finds_a_lone_factory_servo_by_broadcast_and_gives_it_its_id() -> None:
    with ServoBusEmulator([1]) as emu:  # a new servo answers at the factory id 1
        bus = _patient(
            FeetechMotorsBus(port=emu.port, motors={"gripper": Motor(6, "sts3215", MotorNormMode.RANGE_0_100)})
        )
        bus.setup_motor("gripper")  # what lerobot-setup-motors does for each motor in turn
        try:
            assert sorted(emu.servos) == [6]
            assert bus.ping("gripper") == 777
            assert emu.servos[6].register(Register.BAUD_RATE) == 0  # 1 Mbit/s
            emu.power_cycle()  # written after LeRobot's torque-off unlocked the EEPROM: kept
            assert bus.ping("gripper") == 777
        finally:
            bus.port_handler.closePort()
