"""SO10xFollowerHAL against the servo-bus emulator on a real pseudo-terminal."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

pytest.importorskip("serial", reason="needs the 'serial' extra")

from openral_core import Action, ROSConfigError, ROSHardwareError, ROSSafetyViolation
from openral_core.robot import RobotManifest
from openral_hal import HAL, load_robot_manifest
from openral_hal.feetech.calibrate import calibrate
from openral_hal.feetech.calibration import ArmCalibration, load_calibration, save_calibration
from openral_hal.feetech.emulator import ServoBusEmulator
from openral_hal.feetech.hal import SO10xFollowerHAL
from openral_hal.feetech.protocol import RAD_PER_TICK

MANIFEST = load_robot_manifest("so101_follower")
IDS = [j.servo_id for j in MANIFEST.joints]


@pytest.fixture
def emu() -> Iterator[ServoBusEmulator]:
    with ServoBusEmulator([i for i in IDS if i is not None]) as emulator:
        yield emulator


@pytest.fixture
def cal_file(tmp_path: Path) -> Path:
    path = tmp_path / "so101.json"
    save_calibration(ArmCalibration.from_manifest(MANIFEST), path)
    return path


def _hal(emu: ServoBusEmulator, cal_file: Path, **params: object) -> SO10xFollowerHAL:
    return SO10xFollowerHAL(MANIFEST, {"port": emu.port, "calibration": str(cal_file), "timeout_s": 0.02, **params})


def _eventually(check: Callable[[], bool], timeout_s: float = 1.0) -> bool:
    """Fire-and-forget SYNC_WRITEs reach the emulator a moment later; poll for their effect."""
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.002)
    return True


def _action(**targets: float) -> Action:
    return Action(joint_names=list(targets), targets=[list(targets.values())])


def test_is_a_hal_and_params_are_checked(emu: ServoBusEmulator, cal_file: Path) -> None:
    assert isinstance(_hal(emu, cal_file), HAL)
    with pytest.raises(ROSConfigError, match=r"hal\.params\.bogus"):
        SO10xFollowerHAL(MANIFEST, {"emulate": True, "bogus": 1})
    with pytest.raises(ROSConfigError, match="required unless 'emulate'"):
        SO10xFollowerHAL(MANIFEST, {"port": "/dev/ttyACM0"})


def test_connect_enables_torque_holding_present_pose(emu: ServoBusEmulator, cal_file: Path) -> None:
    emu.move_by_hand(2, 2300)
    hal = _hal(emu, cal_file)
    hal.connect()
    try:
        assert hal.is_connected
        assert _eventually(lambda: all(emu.torque().values()))
        assert emu.goals()[2] == 2300  # no jump when torque comes on
        state = hal.read_state()
        assert state.names == MANIFEST.joint_names
        assert state.positions[1] == pytest.approx(252 * RAD_PER_TICK)
        assert state.velocities == [0.0] * 6
    finally:
        hal.disconnect()
    assert not hal.is_connected
    assert _eventually(lambda: not any(emu.torque().values()))  # torque_off_on_disconnect defaults to true
    hal.disconnect()  # idempotent


def test_send_action_moves_the_arm_toward_goal(emu: ServoBusEmulator, cal_file: Path) -> None:
    hal = _hal(emu, cal_file, torque_off_on_disconnect=False)
    with_hal = hal
    with_hal.connect()
    try:
        hal.send_action(_action(shoulder_pan=0.3, elbow_flex=-0.2))
        # The first reading that shows motion (~65 ms before arrival): moving, not teleported.
        readings = [hal.read_state()]
        assert _eventually(lambda: readings.append(hal.read_state()) or readings[-1].positions[0] > 0.0)
        mid = readings[-1]
        assert 0.0 < mid.positions[0] < 0.3
        assert mid.velocities is not None
        assert mid.velocities[0] > 1.0
        assert mid.velocities[2] < -1.0
        assert _eventually(lambda: abs(hal.read_state().positions[0] - 0.3) <= RAD_PER_TICK)
        end = hal.read_state()
        assert end.positions[0] == pytest.approx(0.3, abs=RAD_PER_TICK)
        assert end.positions[2] == pytest.approx(-0.2, abs=RAD_PER_TICK)
        assert end.positions[1] == pytest.approx(0.0)  # unnamed joints keep their target
    finally:
        hal.disconnect()


def test_targets_are_clipped_to_limits_and_bad_values_refused(emu: ServoBusEmulator, cal_file: Path) -> None:
    hal = _hal(emu, cal_file)
    hal.connect()
    try:
        hal.send_action(_action(elbow_flex=10.0))
        cal = ArmCalibration.from_manifest(MANIFEST).joints["elbow_flex"]
        expected = cal.to_ticks(MANIFEST.joint("elbow_flex").upper)
        assert expected <= cal.range_max
        assert _eventually(lambda: emu.goals()[3] == expected)
        with pytest.raises(ROSSafetyViolation):
            hal.send_action(_action(elbow_flex=math.nan))
        with pytest.raises(ROSConfigError, match="no joint 'elbow'"):
            hal.send_action(_action(elbow=0.0))
    finally:
        hal.disconnect()


def test_missing_servo_at_connect_is_named_and_nothing_left_open(emu: ServoBusEmulator, cal_file: Path) -> None:
    emu.missing_ids = {4}
    hal = _hal(emu, cal_file, retries=0)
    with pytest.raises(ROSHardwareError, match=r"wrist_flex \(id 4\)"):
        hal.connect()
    assert not hal.is_connected
    assert not any(emu.torque().values())


def test_bus_gone_mid_run_raises_on_read_and_send(emu: ServoBusEmulator, cal_file: Path) -> None:
    hal = _hal(emu, cal_file)
    hal.connect()
    try:
        emu.disconnect()
        with pytest.raises(ROSHardwareError, match=emu.port):
            hal.read_state()
        with pytest.raises(ROSHardwareError, match=emu.port):
            hal.send_action(_action(shoulder_pan=0.1))
    finally:
        hal.disconnect()


def test_servo_timeout_mid_run_names_port_and_joints(emu: ServoBusEmulator, cal_file: Path) -> None:
    hal = _hal(emu, cal_file, retries=1)
    hal.connect()
    try:
        emu.missing_ids = {6}
        with pytest.raises(ROSHardwareError, match=r"after 2 attempt.*joints: gripper"):
            hal.read_state()
        emu.missing_ids = set()
        assert len(hal.read_state().positions) == 6  # recovers once the servo answers again
    finally:
        hal.disconnect()


def test_estop_holds_present_position(cal_file: Path) -> None:
    target = 2048 + round(1.5 / RAD_PER_TICK)
    # A tenth of the servo's speed: about 3 s to the target, so the stop lands mid-motion however loaded.
    with ServoBusEmulator([i for i in IDS if i is not None], speed_ticks_s=300.0) as emu:
        hal = _hal(emu, cal_file)
        hal.connect()
        try:
            hal.send_action(_action(shoulder_pan=1.5))
            assert _eventually(lambda: emu.positions()[1] > 2048, timeout_s=5.0)  # under way
            hal.estop()
            assert _eventually(lambda: emu.goals()[1] < target)
            held = emu.goals()[1]
            assert held > 2048
            assert _eventually(lambda: abs(emu.positions()[1] - held) <= 1)  # it stops there
            time.sleep(0.05)
            assert abs(emu.positions()[1] - held) <= 1  # and stays
            assert all(emu.torque().values())
        finally:
            hal.disconnect()


def test_estop_torque_off(emu: ServoBusEmulator, cal_file: Path) -> None:
    hal = _hal(emu, cal_file, estop_torque_off=True)
    hal.connect()
    try:
        hal.estop()
        assert _eventually(lambda: not any(emu.torque().values()))
    finally:
        hal.disconnect()


def test_emulate_param_runs_without_an_arm() -> None:
    hal = SO10xFollowerHAL(MANIFEST, {"emulate": True})
    hal.connect()
    try:
        assert hal.emulator is not None
        hal.send_action(_action(wrist_roll=0.1))
        assert _eventually(lambda: abs(hal.read_state().positions[4] - 0.1) <= RAD_PER_TICK, timeout_s=5.0)
    finally:
        hal.disconnect()
    assert hal.emulator is None


def test_read_before_connect_raises(cal_file: Path) -> None:
    hal = SO10xFollowerHAL(MANIFEST, {"port": "/dev/null", "calibration": str(cal_file)})
    with pytest.raises(ROSHardwareError, match="not connected"):
        hal.read_state()


def test_calibrate_records_homing_and_range(emu: ServoBusEmulator, tmp_path: Path) -> None:
    manifest: RobotManifest = MANIFEST
    now = [0.0]
    sweep = iter(range(0, 400, 40))

    def hand_to_middle(_: str) -> str:
        for i in IDS:
            assert i is not None
            emu.move_by_hand(i, 2000 + i)
        return ""

    def hand_sweep(period: float) -> None:
        now[0] += period
        step = next(sweep, 0)
        for i in IDS:
            assert i is not None
            emu.move_by_hand(i, 2000 + i + (step if step % 80 else -step))

    out = tmp_path / "cal.yaml"
    cal = calibrate(
        manifest,
        emu.port,
        out,
        record_s=0.2,
        sample_period_s=0.02,
        directions={"gripper": -1},
        prompt=hand_to_middle,
        say=lambda _: None,
        clock=lambda: now[0],
        sleep=hand_sweep,
    )
    assert load_calibration(out) == cal
    pan = cal.joints["shoulder_pan"]
    assert pan.homing_ticks == 2001
    assert pan.range_min < 2001 - 200
    assert pan.range_max > 2001 + 200
    assert cal.joints["gripper"].direction == -1
    assert not any(emu.torque().values())


def test_calibrate_refuses_unmoved_joints(emu: ServoBusEmulator, tmp_path: Path) -> None:
    now = [0.0]

    def tick(period: float) -> None:
        now[0] += period

    with pytest.raises(ROSHardwareError, match="barely moved"):
        calibrate(
            MANIFEST,
            emu.port,
            tmp_path / "c.json",
            record_s=0.05,
            prompt=lambda _: "",
            say=lambda _: None,
            clock=lambda: now[0],
            sleep=tick,
        )
    assert not (tmp_path / "c.json").exists()


def test_calibration_path_with_tilde_is_expanded(
    cal_file: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    home = tmp_path / "home"
    (home / ".config" / "openral").mkdir(parents=True)
    (home / ".config" / "openral" / "so101_follower.json").write_bytes(cal_file.read_bytes())
    monkeypatch.setenv("HOME", str(home))
    hal = SO10xFollowerHAL(MANIFEST, {"port": "/dev/null", "calibration": "~/.config/openral/so101_follower.json"})
    assert hal.calibration == load_calibration(cal_file)


def test_calibration_that_is_not_a_regular_file_is_a_config_error() -> None:
    with pytest.raises(ROSConfigError) as info:
        SO10xFollowerHAL(MANIFEST, {"port": "/dev/null", "calibration": "/dev/zero"})
    assert info.value.field == "hal.params.calibration"


def test_baudrate_beyond_any_serial_adapter_is_a_config_error(cal_file: Path) -> None:
    with pytest.raises(ROSConfigError) as info:
        SO10xFollowerHAL(MANIFEST, {"port": "/dev/null", "calibration": str(cal_file), "baudrate": 10**30})
    assert info.value.field == "hal.params.baudrate"
