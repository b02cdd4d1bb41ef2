"""LeRobot's own SO-101 driver under openral (``lerobot_robot``), against the Feetech emulator on a pty.

LeRobot's ``SO101Follower`` and ``FeetechMotorsBus`` (with the Feetech SDK) open the emulator's
pseudo-terminal like a USB adapter; every number checked here went through LeRobot's
normalisation and openral's conversion back to the manifest's radians.
"""

from __future__ import annotations

import json
import math
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

pytestmark = pytest.mark.usefixtures("quick_thread_switches")

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

pytest.importorskip("lerobot", reason=LEROBOT_REASON)
pytest.importorskip("scservo_sdk", reason=LEROBOT_REASON)

from click.testing import CliRunner  # noqa: E402

from openral_cli.main import cli  # noqa: E402
from openral_core import Action, ControlMode, RobotEnvironment, ROSConfigError, ROSHardwareError  # noqa: E402
from openral_hal.feetech import protocol as p  # noqa: E402
from openral_hal.feetech.emulator import ServoBusEmulator  # noqa: E402
from openral_hal.feetech.protocol import Instruction, Register  # noqa: E402
from openral_hal.lerobot.robot_hal import LeRobotRobotHAL  # noqa: E402
from openral_hal.lerobot.units import JointUnits, UnitConversion  # noqa: E402
from openral_hal.manifests import load_robot_manifest  # noqa: E402
from openral_runner.factory import build_runner  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
RANGES = {1: (700, 3300), 2: (800, 3200), 3: (900, 3100), 4: (1000, 3000), 5: (0, 4095), 6: (2000, 3400)}
"""Calibrated tick ranges per servo id, as lerobot-calibrate would record them."""
START = {1: 2100, 2: 1900, 3: 2300, 4: 1800, 5: 2048, 6: 2200}
SO101 = load_robot_manifest("so101_follower")


def write_calibration(folder: Path, arm_id: str) -> Path:
    """A LeRobot calibration file (lerobot-calibrate's format) for one SO-101 arm."""
    data = {
        name: {"id": i, "drive_mode": 0, "homing_offset": 0, "range_min": RANGES[i][0], "range_max": RANGES[i][1]}
        for i, name in enumerate(MOTORS, start=1)
    }
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{arm_id}.json"
    path.write_text(json.dumps(data), encoding="utf-8")
    return path


def expected_radians(ticks: dict[int, int]) -> np.ndarray:
    """LeRobot's normalisation (degrees about the range's middle; gripper 0..100) then the manifest's radians."""
    out = []
    for servo_id, joint in zip(range(1, 7), SO101.joints, strict=True):
        low, high = RANGES[servo_id]
        if joint.name == "gripper":
            fraction = (min(max(ticks[servo_id], low), high) - low) / (high - low)
            out.append(joint.lower + fraction * (joint.upper - joint.lower))
        else:
            out.append(math.radians((ticks[servo_id] - (low + high) / 2) * 360 / 4095))
    return np.array(out)


def wait_until(condition: Callable[[], bool], timeout: float = 10.0) -> None:
    """Poll ``condition`` until it holds; fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.005)


@pytest.fixture
def bus() -> Iterator[ServoBusEmulator]:
    with ServoBusEmulator(range(1, 7), initial_ticks=START) as emulator:
        yield emulator


@pytest.fixture
def arm(tmp_path: Path, bus: ServoBusEmulator) -> Iterator[LeRobotRobotHAL]:
    write_calibration(tmp_path, "arm")
    hal = LeRobotRobotHAL(
        SO101, {"type": "so101_follower", "port": bus.port, "id": "arm", "calibration_dir": str(tmp_path)}
    )
    try:
        yield hal
    finally:
        hal.disconnect()


# -- configuration, no port opened -------------------------------------------------------------


def test_wrong_key_unknown_type_and_cameras_name_their_field(tmp_path: Path) -> None:
    write_calibration(tmp_path, "arm")
    base = {"type": "so101_follower", "port": "/dev/does-not-exist", "id": "arm", "calibration_dir": str(tmp_path)}
    with pytest.raises(ROSConfigError, match=r"hal\.params\.prot: .*allowed keys: .*port"):
        LeRobotRobotHAL(SO101, {**base, "prot": "x"})
    with pytest.raises(ROSConfigError, match=r"hal\.params\.type: .*'so101_folower'.*did you mean 'so101_follower'"):
        LeRobotRobotHAL(SO101, {**base, "type": "so101_folower"})
    without_port = {key: value for key, value in base.items() if key != "port"}
    with pytest.raises(ROSConfigError, match=r"hal\.params\.port: Missing required field"):
        LeRobotRobotHAL(SO101, without_port)
    camera = {"type": "opencv", "index_or_path": 0, "fps": 30, "width": 640, "height": 480}
    with pytest.raises(ROSConfigError, match=r"hal\.params\.cameras: .*front") as caught:
        LeRobotRobotHAL(SO101, {**base, "cameras": {"front": camera}})
    # The fix the message gives is a sensor block that validates as it is.
    block = yaml.safe_load(str(caught.value).split("move them under sensors: ")[1].rstrip(")"))
    assert block == [
        {
            "sensor_id": "front",
            "backend": "lerobot_camera",
            "width": 640,
            "height": 480,
            "fps": 30,
            "backend_params": {"type": "opencv", "index_or_path": 0},
        }
    ]
    deployment = yaml.safe_load((ROOT / "deployments" / "so101_lerobot.yaml").read_text(encoding="utf-8"))
    deployment["hal"]["params"] = base
    deployment["sensors"] = block
    path = tmp_path / "with_camera.yaml"
    path.write_text(yaml.safe_dump(deployment), encoding="utf-8")
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 0, result.output
    assert "1 sensor(s)" in result.output


def test_missing_calibration_names_the_file_and_the_command(tmp_path: Path) -> None:
    params = {"type": "so101_follower", "port": "/dev/ttyACM7", "id": "lefty", "calibration_dir": str(tmp_path)}
    with pytest.raises(ROSConfigError) as caught:
        LeRobotRobotHAL(SO101, params)
    message = str(caught.value)
    assert str(tmp_path / "lefty.json") in message
    assert "lerobot-calibrate --robot.type=so101_follower --robot.port=/dev/ttyACM7 --robot.id=lefty" in message


def test_a_manifest_that_is_not_the_robot_is_refused(tmp_path: Path) -> None:
    write_calibration(tmp_path, "arm")
    params = {"type": "so101_follower", "port": "/dev/x", "id": "arm", "calibration_dir": str(tmp_path)}
    with pytest.raises(ROSConfigError, match=r"hal\.robot_id: .*has no joint left_shoulder_pan"):
        LeRobotRobotHAL(load_robot_manifest("bi_so101_follower"), params)


def test_validate_builds_the_deployment_without_opening_the_port(tmp_path: Path) -> None:
    write_calibration(tmp_path, "my_follower")
    text = (ROOT / "deployments" / "so101_lerobot.yaml").read_text(encoding="utf-8")
    text = text.replace("id: my_follower", f"id: my_follower\n    calibration_dir: {tmp_path}")
    path = tmp_path / "arm.yaml"
    path.write_text(text.replace("/dev/ttyACM0", str(tmp_path / "no-such-port")), encoding="utf-8")
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 0, result.output
    assert "lerobot_robot" in result.output


# -- connected through LeRobot's driver ----------------------------------------------------------


def test_connect_writes_the_calibration_and_holds_the_pose(arm: LeRobotRobotHAL, bus: ServoBusEmulator) -> None:
    # A stale goal left in the servos by an earlier session: torque-on must not drive to it.
    for servo in bus.servos.values():
        servo.memory[Register.GOAL_POSITION : Register.GOAL_POSITION + 2] = p.u16(3000)
    arm.connect()
    assert all(bus.torque().values())
    assert bus.goals() == START
    assert bus.positions() == START
    for servo_id, (low, high) in RANGES.items():
        memory = bus.servos[servo_id].memory
        assert p.from_u16(memory, Register.MIN_POSITION_LIMIT) == low
        assert p.from_u16(memory, Register.MAX_POSITION_LIMIT) == high


def test_state_is_lerobots_reading_in_the_manifests_radians(arm: LeRobotRobotHAL, bus: ServoBusEmulator) -> None:
    arm.connect()
    state = arm.read_state()
    assert state.names == SO101.joint_names
    np.testing.assert_allclose(state.positions, expected_radians(START), atol=1e-9)


def test_an_action_reaches_the_servos_in_lerobots_units(arm: LeRobotRobotHAL, bus: ServoBusEmulator) -> None:
    arm.connect()
    target = {"shoulder_pan": 0.4, "gripper": SO101.joints[-1].upper}
    arm.send_action(
        Action(control_mode=ControlMode.JOINT_POSITION, joint_names=list(target), targets=[list(target.values())])
    )
    wait_until(lambda: bus.goals()[1] != START[1])  # a sync write has no reply: wait for the servos to take it
    goals = bus.goals()
    pan_ticks = (RANGES[1][0] + RANGES[1][1]) / 2 + math.degrees(0.4) * 4095 / 360
    assert goals[1] == pytest.approx(pan_ticks, abs=1)
    assert goals[6] == RANGES[6][1]
    assert {i: goals[i] for i in (2, 3, 4, 5)} == {i: START[i] for i in (2, 3, 4, 5)}
    wait_until(lambda: bus.positions()[1] == goals[1])
    np.testing.assert_allclose(arm.read_state().positions[0], 0.4, atol=2 * 2 * math.pi / 4095)


def test_a_target_beyond_the_manifest_is_clipped_and_disconnect_leaves_torque_off(
    arm: LeRobotRobotHAL, bus: ServoBusEmulator
) -> None:
    arm.connect()
    arm.send_action(Action(control_mode=ControlMode.JOINT_POSITION, joint_names=["elbow_flex"], targets=[[3.0]]))
    upper = SO101.joints[2].upper
    expected = (RANGES[3][0] + RANGES[3][1]) / 2 + math.degrees(upper) * 4095 / 360
    wait_until(lambda: bus.goals()[3] != START[3])
    assert bus.goals()[3] == pytest.approx(expected, abs=1)
    arm.disconnect()
    assert not any(bus.torque().values())
    assert not arm.is_connected


def test_a_second_runner_on_the_port_is_refused(arm: LeRobotRobotHAL, bus: ServoBusEmulator, tmp_path: Path) -> None:
    arm.connect()
    other = LeRobotRobotHAL(
        SO101, {"type": "so101_follower", "port": bus.port, "id": "arm", "calibration_dir": str(tmp_path)}
    )
    with pytest.raises(ROSHardwareError, match="in use"):
        other.connect()
    assert all(bus.torque().values()), "the refused runner must not touch the first one's arm"


def test_a_missing_servo_fails_connect_with_torque_off_and_the_port_free(
    arm: LeRobotRobotHAL, bus: ServoBusEmulator
) -> None:
    bus.missing_ids = {4}
    with pytest.raises(ROSHardwareError, match="failed to connect"):
        arm.connect()
    assert not any(bus.torque().values())
    bus.missing_ids = set()
    arm.connect()
    assert arm.is_connected


# -- openral deploy through LeRobot's driver -----------------------------------------------------


class GoalWatch:
    """The goal-position writes a deployment's ticks make (after torque on), and positions sampled then."""

    def __init__(self, bus: ServoBusEmulator, at: int) -> None:
        self.bus = bus
        self.at = at
        self.ticks = 0
        self.samples: list[tuple[dict[int, int], dict[int, int]]] = []
        self.running = threading.Event()
        self._torque_on = False
        bus.on_request = self._on_request

    def _on_request(self, packet: p.Packet) -> None:
        params = packet.params
        if packet.code == Instruction.WRITE and params[0] == Register.TORQUE_ENABLE:
            self._torque_on = params[1] == 1
        elif self._torque_on and packet.code == Instruction.SYNC_WRITE and params[0] == Register.GOAL_POSITION:
            self.ticks += 1
            if self.ticks >= self.at:
                self.running.set()


def deploy_and_interrupt(deployment: Path, buses: list[ServoBusEmulator], deploy_process, ticks: int = 45) -> None:
    """``openral deploy`` the file until every bus took ``ticks`` goals, then Ctrl-C; check what the servos did.

    The servos followed every commanded goal while it ran, and every one is limp after the stop.
    """
    watches = [GoalWatch(bus, at=ticks) for bus in buses]
    proc = deploy_process(["deploy", "--config", str(deployment), "--json"])
    # Sample goal and position together while it runs: the servos follow what the ticks command.
    while not all(watch.running.wait(0.02) for watch in watches):
        assert proc.proc.poll() is None, proc.stderr
        for watch in watches:
            if watch.ticks:
                watch.samples.append((watch.bus.goals(), watch.bus.positions()))
    assert all(all(bus.torque().values()) for bus in buses)
    proc.signal_group(signal.SIGINT)
    code, stdout = proc.finish(timeout=60)
    assert code == 130, proc.stderr
    for bus in buses:
        assert not any(bus.torque().values()), "Ctrl-C leaves every servo limp"
    result = json.loads(stdout)
    # Start-up writes up to two holds (goal := present) once torque is on; every other goal is a tick's.
    assert result["n_ticks"] >= ticks - 2
    assert result["effective_rate_hz"] == pytest.approx(30, rel=0.1)
    for watch in watches:
        goals = np.array([[g[i] for i in range(1, 7)] for g, _ in watch.samples])
        positions = np.array([[q[i] for i in range(1, 7)] for _, q in watch.samples])
        moving = np.ptp(goals, axis=0) > 20
        assert moving.sum() >= 3, "the hello wave moves several joints of every arm"
        # A servo at 3000 ticks/s reaches each 30 Hz goal of this slow wave within a few ticks of it.
        assert np.abs(goals[:, moving] - positions[:, moving]).max() <= 40


def test_deploy_runs_hello_through_lerobots_driver_and_sigint_leaves_torque_off(
    tmp_path: Path, bus: ServoBusEmulator, deploy_process
) -> None:
    write_calibration(tmp_path, "my_follower")
    text = (ROOT / "deployments" / "so101_lerobot.yaml").read_text(encoding="utf-8")
    text = text.replace("/dev/ttyACM0", bus.port).replace(
        "id: my_follower", f"id: my_follower\n    calibration_dir: {tmp_path}"
    )
    path = tmp_path / "arm.yaml"
    path.write_text(text, encoding="utf-8")
    deploy_and_interrupt(path, [bus], deploy_process)


def test_deploy_runs_a_bimanual_so101_on_two_buses_and_sigint_leaves_both_limp(tmp_path: Path, deploy_process) -> None:
    write_calibration(tmp_path, "my_pair_left")
    write_calibration(tmp_path, "my_pair_right")
    with ServoBusEmulator(range(1, 7), initial_ticks=START) as left, ServoBusEmulator(range(1, 7)) as right:
        text = (ROOT / "deployments" / "bi_so101_lerobot.yaml").read_text(encoding="utf-8")
        text = text.replace("/dev/ttyACM0", left.port).replace("/dev/ttyACM1", right.port)
        path = tmp_path / "pair.yaml"
        path.write_text(text.replace("id: my_pair", f"id: my_pair\n    calibration_dir: {tmp_path}"), encoding="utf-8")
        deploy_and_interrupt(path, [left, right], deploy_process)


# -- a bimanual SO-101: two buses, one manifest ------------------------------------------------------


def test_bimanual_so101_reads_each_arm_from_its_own_bus(tmp_path: Path) -> None:
    write_calibration(tmp_path, "pair_left")
    write_calibration(tmp_path, "pair_right")
    with ServoBusEmulator(range(1, 7), initial_ticks=START) as left, ServoBusEmulator(range(1, 7)) as right:
        text = (ROOT / "deployments" / "bi_so101_lerobot.yaml").read_text(encoding="utf-8")
        text = text.replace("/dev/ttyACM0", left.port).replace("/dev/ttyACM1", right.port)
        text = text.replace("id: my_pair", f"id: pair\n    calibration_dir: {tmp_path}")
        path = tmp_path / "pair.yaml"
        path.write_text(text, encoding="utf-8")
        runner, skill = build_runner(RobotEnvironment.from_yaml(path), base_dir=tmp_path)
        skill.configure()
        skill.activate()
        runner.activate()
        try:
            state = runner.hal.read_state()
            np.testing.assert_allclose(state.positions[:6], expected_radians(START), atol=1e-9)
            np.testing.assert_allclose(state.positions[6:], expected_radians(dict.fromkeys(range(1, 7), 2048)))
            result = runner.run(45)
            moved_left, moved_right = left.goals(), right.goals()
        finally:
            runner.deactivate()
            skill.shutdown()
        assert result.n_ticks == 45
        assert result.failed_ticks == 0
        sent = np.array([t.sent_action for t in runner.recent_ticks])
        # Both arms follow the wave: each bus got goals away from where its arm started.
        assert sum(moved_left[i] != START[i] for i in range(1, 7)) >= 3
        assert sum(moved_right[i] != 2048 for i in range(1, 7)) >= 3
        assert np.ptp(sent[:, :6], axis=0).max() > 0.05
        assert np.ptp(sent[:, 6:], axis=0).max() > 0.05
        assert not any(left.torque().values())
        assert not any(right.torque().values())


@pytest.mark.parametrize(("use_degrees", "units"), [(True, "degrees"), (False, "range")])
def test_the_robot_and_a_lerobot_policy_read_joints_in_the_same_units(
    tmp_path: Path, use_degrees: bool, units: JointUnits
) -> None:
    """A policy recorded with lerobot-record on this arm gets back, through openral, the numbers it was trained on."""
    write_calibration(tmp_path, "arm")
    params = {"type": "so101_follower", "port": "/dev/x", "id": "arm", "calibration_dir": str(tmp_path)}
    hal = LeRobotRobotHAL(SO101, {**params, "use_degrees": use_degrees})
    policy = UnitConversion(SO101, units)
    assert hal.units.norms == policy.norms
    lerobot_values = np.array([12.5, -40.0, 80.0, -3.0, 99.0, 37.0])
    np.testing.assert_allclose(policy.to_policy(hal.units.to_radians(lerobot_values)), lerobot_values)


def test_a_forced_stop_turns_torque_off_while_a_read_is_stuck(arm: LeRobotRobotHAL, bus: ServoBusEmulator) -> None:
    arm.connect()
    bus.mute = True  # the servos execute requests but no reply comes back: the next read hangs in retries
    failures: list[BaseException] = []

    def read_until_it_fails() -> None:
        try:
            arm.read_state()
        except ROSHardwareError as exc:
            failures.append(exc)

    stuck = threading.Thread(target=read_until_it_fails, daemon=True)
    stuck.start()
    wait_until(lambda: bus.requests > 0 and stuck.is_alive())
    stopper = threading.Thread(target=arm.disconnect, daemon=True)
    stopper.start()
    wait_until(lambda: not any(bus.torque().values()), timeout=0.5)
    assert stuck.is_alive(), "torque went off before the stuck read gave up"
    stuck.join(30)
    stopper.join(30)
    assert len(failures) == 1
    assert not arm.is_connected


# -- a third-party LeRobot robot package ---------------------------------------------------------------

PLUGIN_CONFIG = """
from dataclasses import dataclass

from lerobot.robots.config import RobotConfig
from lerobot.robots.so_follower.config_so_follower import SOFollowerConfig


@RobotConfig.register_subclass("third_party_arm")
@dataclass
class ThirdPartyArmConfig(RobotConfig, SOFollowerConfig):
    pass
"""
PLUGIN_ROBOT = """
from lerobot.robots.so_follower.so_follower import SOFollower

from .config_third_party_arm import ThirdPartyArmConfig


class ThirdPartyArm(SOFollower):
    config_class = ThirdPartyArmConfig
    name = "third_party_arm"
"""


def test_a_robot_from_an_installed_lerobot_robot_package_is_driven(
    tmp_path: Path, bus: ServoBusEmulator, installed_package
) -> None:
    installed_package(
        "lerobot_robot_third_party_arm",
        "from .config_third_party_arm import ThirdPartyArmConfig\nfrom .third_party_arm import ThirdPartyArm\n",
        files={"config_third_party_arm.py": PLUGIN_CONFIG, "third_party_arm.py": PLUGIN_ROBOT},
        importable=True,
    )
    write_calibration(tmp_path, "arm")
    hal = LeRobotRobotHAL(
        SO101, {"type": "third_party_arm", "port": bus.port, "id": "arm", "calibration_dir": str(tmp_path)}
    )
    assert type(hal.robot).__name__ == "ThirdPartyArm"
    hal.connect()
    try:
        np.testing.assert_allclose(hal.read_state().positions, expected_radians(START), atol=1e-9)
        hal.send_action(Action(control_mode=ControlMode.JOINT_POSITION, joint_names=["wrist_flex"], targets=[[0.2]]))
        wait_until(lambda: bus.positions()[4] != START[4])
    finally:
        hal.disconnect()
    assert not any(bus.torque().values())


def test_an_arm_configured_to_hold_keeps_torque_on_when_the_run_stops(tmp_path: Path, bus: ServoBusEmulator) -> None:
    write_calibration(tmp_path, "arm")
    params = {"type": "so101_follower", "port": bus.port, "id": "arm", "calibration_dir": str(tmp_path)}
    hal = LeRobotRobotHAL(SO101, {**params, "disable_torque_on_disconnect": False})
    hal.connect()
    hal.disconnect()
    assert all(bus.torque().values()), "LeRobot's own disable_torque_on_disconnect: false is honoured"
    assert not hal.is_connected
