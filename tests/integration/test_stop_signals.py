"""``openral deploy`` on the serial arm, stopped the way users and service managers stop it.

Each test starts ``uv run openral deploy`` in its own process group against a servo-bus
emulator on a pseudo-terminal that lives in the test process, signals the group (so uv forwards a
second copy, as it does under systemd or a terminal's Ctrl-C), and reads the servos' torque
registers at the end: whatever the phase and however many signals, the arm ends limp
(``torque_off_on_disconnect: true``) and the RunResult is printed.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("serial", reason="needs the 'serial' extra (pyserial)")

from openral_hal.feetech import protocol as p
from openral_hal.feetech.calibration import ArmCalibration, save_calibration
from openral_hal.feetech.emulator import ServoBusEmulator
from openral_hal.feetech.protocol import Instruction, Register
from openral_hal.manifests import load_robot_manifest

SERVO_IDS = range(1, 7)

DEPLOYMENT = """\
name: serial_signals
rate_hz: 30
hal:
  robot_id: so101_follower
  adapter: so10x_follower
  params:
    port: {port}
    calibration: {calibration}
    timeout_s: {timeout_s}
    retries: {retries}
    torque_off_on_disconnect: true
vla:
  id: hello
  params: {{amplitude_rad: 0.2, frequency_hz: 0.5}}
safety: {{client: envelope}}
"""


@pytest.fixture
def bus() -> Iterator[ServoBusEmulator]:
    with ServoBusEmulator(SERVO_IDS) as emulator:
        yield emulator


def _deployment(tmp_path: Path, bus: ServoBusEmulator, *, timeout_s: float = 0.02, retries: int = 2) -> Path:
    calibration = tmp_path / "so101.json"
    save_calibration(ArmCalibration.from_manifest(load_robot_manifest("so101_follower")), calibration)
    path = tmp_path / "arm.yaml"
    path.write_text(
        DEPLOYMENT.format(port=bus.port, calibration=calibration, timeout_s=timeout_s, retries=retries),
        encoding="utf-8",
    )
    return path


class TickGoals:
    """Counts the goal positions the runner's ticks write: those sent once torque is on.

    Start-up writes one goal (hold the present pose) before it turns torque on; every goal after
    that is one tick's command, so a run that was signalled after ``count`` of them ran at least
    ``count`` ticks, however slowly the machine ticked. ``running`` is set after ``at`` of them.
    """

    def __init__(self, bus: ServoBusEmulator, at: int = 10) -> None:
        self.count = 0
        self.running = threading.Event()
        self._at = at
        self._torque_on = False
        self._previous = bus.on_request
        bus.on_request = self._on_request

    def _on_request(self, packet: p.Packet) -> None:
        if self._previous is not None:
            self._previous(packet)
        if _is_torque_write(packet, 1):
            self._torque_on = True
        elif self._torque_on and packet.code == Instruction.SYNC_WRITE and packet.params[0] == Register.GOAL_POSITION:
            self.count += 1
            if self.count >= self._at:
                self.running.set()


def _is_torque_write(packet: p.Packet, value: int) -> bool:
    params = packet.params
    if packet.code == Instruction.WRITE:
        return len(params) == 2 and params[0] == Register.TORQUE_ENABLE and params[1] == value
    if packet.code == Instruction.SYNC_WRITE:
        return params[0] == Register.TORQUE_ENABLE and len(params) > 3 and params[3] == value
    return False


def _result(stdout: str) -> dict:
    return json.loads(stdout)


def _all_limp(bus: ServoBusEmulator) -> bool:
    return not any(bus.torque().values())


def test_group_sigterm_through_uv_stops_once_with_torque_off(tmp_path: Path, bus, deploy_process) -> None:
    goals = TickGoals(bus)
    proc = deploy_process(["deploy", "--config", str(_deployment(tmp_path, bus)), "--json"], through_uv=True)
    assert goals.running.wait(60), proc.stderr
    assert all(bus.torque().values())
    ticked = goals.count
    proc.signal_group(signal.SIGTERM)
    code, stdout = proc.finish(timeout=30)
    assert code == 143, proc.stderr
    result = _result(stdout)
    assert result["stop_reason"] == "signal:SIGTERM"
    assert result["n_ticks"] >= ticked  # the printed RunResult counts every tick that drove the arm
    assert _all_limp(bus)
    assert "Traceback" not in proc.stderr
    assert "forced" not in proc.stderr


def test_repeated_sigint_is_one_orderly_stop(tmp_path: Path, bus, deploy_process) -> None:
    goals = TickGoals(bus)
    proc = deploy_process(["deploy", "--config", str(_deployment(tmp_path, bus)), "--json"], through_uv=True)
    assert goals.running.wait(60), proc.stderr
    proc.signal_group(signal.SIGINT)
    proc.wait_for("SIGINT: stopping after this tick")
    time.sleep(0.4)  # the user presses Ctrl-C again a moment later, while the stop is under way
    proc.signal_group(signal.SIGINT)
    code, stdout = proc.finish(timeout=30)
    assert code == 130, proc.stderr
    assert _result(stdout)["stop_reason"] == "signal:SIGINT"
    assert _all_limp(bus)
    assert "Aborted" not in proc.stderr
    assert "Traceback" not in proc.stderr


def test_sigterm_the_instant_torque_goes_on_unwinds_to_torque_off(tmp_path: Path, bus, deploy_process) -> None:
    holder: list = []
    torque_on = threading.Event()

    def on_request(packet: p.Packet) -> None:
        if _is_torque_write(packet, 1) and not torque_on.is_set():
            torque_on.set()
            os.killpg(holder[0].proc.pid, signal.SIGTERM)  # start-up is still under way

    bus.on_request = on_request
    holder.append(deploy_process(["deploy", "--config", str(_deployment(tmp_path, bus)), "--json"], through_uv=True))
    code, stdout = holder[0].finish(timeout=60)
    assert torque_on.is_set(), holder[0].stderr
    assert code == 143, holder[0].stderr
    result = _result(stdout)
    assert result["stop_reason"] == "signal:SIGTERM"
    assert result["n_ticks"] <= 1
    assert _all_limp(bus)


def test_signal_while_closing_does_not_skip_torque_off(tmp_path: Path, bus, deploy_process) -> None:
    goals = TickGoals(bus)
    holder: list = []
    closing = threading.Event()
    previous = bus.on_request

    def on_request(packet: p.Packet) -> None:
        if previous is not None:
            previous(packet)
        if _is_torque_write(packet, 0) and not closing.is_set():
            closing.set()
            os.killpg(holder[0].proc.pid, signal.SIGTERM)  # a second stop arrives mid-disconnect

    bus.on_request = on_request
    holder.append(deploy_process(["deploy", "--config", str(_deployment(tmp_path, bus)), "--json"], through_uv=True))
    assert goals.running.wait(60), holder[0].stderr
    holder[0].signal_group(signal.SIGTERM)
    code, stdout = holder[0].finish(timeout=30)
    assert closing.is_set()
    assert code == 143, holder[0].stderr
    assert _result(stdout)["stop_reason"] == "signal:SIGTERM"
    assert _all_limp(bus)


def test_two_more_signals_within_a_second_force_torque_off_and_exit(tmp_path: Path, bus, deploy_process) -> None:
    # Slow transactions (1 s per attempt, 10 retries: the most a deployment allows): once the replies
    # stop, a tick is stuck for 11 s.
    path = _deployment(tmp_path, bus, timeout_s=1.0, retries=10)
    goals = TickGoals(bus)
    proc = deploy_process(["deploy", "--config", str(path), "--json"], through_uv=True)
    assert goals.running.wait(60), proc.stderr
    bus.mute = True  # the reply line breaks: the tick thread waits in read_state
    started = time.monotonic()
    # The user hammers Ctrl-C (a signal every 0.35 s) until the process is gone.
    while proc.proc.poll() is None and time.monotonic() - started < 10.0:
        proc.signal_group(signal.SIGTERM)
        time.sleep(0.35)
    code, _stdout = proc.finish(timeout=30)
    # About 1.5 s (two signals within a second, then at most 1 s for the emergency actions).
    assert time.monotonic() - started < 8.0, "the escape is bounded, not the 11 s stuck transaction"
    assert code == 143, proc.stderr
    assert "forced stop" in proc.stderr
    assert _all_limp(bus), "the broadcast torque-off goes out even with the bus stuck"


def test_second_runner_on_the_same_bus_is_refused_and_the_first_keeps_driving(
    tmp_path: Path, bus, deploy_process
) -> None:
    path = _deployment(tmp_path, bus)
    goals = TickGoals(bus)
    first = deploy_process(["deploy", "--config", str(path), "--json"])
    assert goals.running.wait(60), first.stderr
    second = deploy_process(["deploy", "--config", str(path), "--json"])
    code, stdout = second.finish(timeout=60)
    assert code == 1
    assert stdout == ""
    errors = [line for line in second.stderr_lines if line.startswith("error:")]
    assert len(errors) == 1, second.stderr
    assert bus.port in errors[0]
    assert f"pid {first.proc.pid}" in errors[0], "names the process holding the bus"
    assert "openral_cli deploy" in errors[0]
    # The refused runner wrote nothing that stopped the first: its arm still has torque and moves.
    assert all(bus.torque().values())
    goals_before = bus.goals()
    deadline = time.monotonic() + 10
    while bus.goals() == goals_before and time.monotonic() < deadline:
        time.sleep(0.02)
    assert bus.goals() != goals_before
    first.signal_group(signal.SIGTERM)
    code, stdout = first.finish(timeout=30)
    assert code == 143
    assert _all_limp(bus)
