"""Record an SO-10x arm's calibration: its middle pose and each joint's range of motion.

The arm's torque is switched off so a person can move it by hand. First they place every joint
in the middle of its range (the model's zero pose) and confirm; that reading becomes each
joint's ``homing_ticks``. Then, while they move every joint through its whole range, present
positions are sampled until ``record_s`` has passed (or ``stop()`` says so); the smallest and
largest readings become ``range_min``/``range_max``. Input, clock and sleep are injectable so
the procedure runs against the emulator in tests.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from pathlib import Path

from openral_core.errors import ROSHardwareError
from openral_core.robot import RobotManifest
from openral_hal.feetech import protocol as p
from openral_hal.feetech.bus import DEFAULT_BAUDRATE, FeetechBus
from openral_hal.feetech.calibration import ArmCalibration, JointCalibration, save_calibration
from openral_hal.feetech.protocol import Register

MIN_RANGE_TICKS = 20


def calibrate(
    manifest: RobotManifest,
    port: str,
    output: Path,
    *,
    baudrate: int = DEFAULT_BAUDRATE,
    record_s: float = 15.0,
    sample_period_s: float = 0.02,
    directions: Mapping[str, int] | None = None,
    prompt: Callable[[str], object] = lambda message: input(f"{message}: "),
    say: Callable[[str], object] = print,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], object] = time.sleep,
    stop: Callable[[], bool] = lambda: False,
) -> ArmCalibration:
    """Walk a person through calibrating the arm on ``port`` and write ``output`` (JSON or YAML).

    Args:
        manifest: The robot; every joint needs a ``servo_id``.
        port: Serial device of the arm's bus.
        output: Calibration file to write.
        record_s: How long to record the range of motion.
        sample_period_s: Pause between position samples while recording.
        directions: ``-1`` for joints whose servo turns against the model's positive sense.
        prompt: Shows a message and waits for the person to confirm (``input`` by default).
        say: Prints progress messages.
        clock, sleep: Time source and pause used while recording.
        stop: Polled while recording; ``True`` ends the recording early.

    Returns:
        The calibration written to ``output``.

    Raises:
        ROSHardwareError: The bus fails, a servo is missing, or a joint was not moved.
        ROSConfigError: A joint has no ``servo_id``.
    """
    nominal = ArmCalibration.from_manifest(manifest)
    names = manifest.joint_names
    ids = [nominal.joints[name].servo_id for name in names]
    signs = dict(directions or {})
    with FeetechBus(port, baudrate=baudrate) as bus:
        missing = bus.find(ids)
        if missing:
            raise ROSHardwareError(f"calibration on {port}: servo(s) {missing} did not answer a ping")
        bus.sync_write(Register.TORQUE_ENABLE, dict.fromkeys(ids, b"\x00"))
        prompt("Torque is off. Move every joint to the middle of its range, then press Enter")
        homing = _read_positions(bus, ids)
        say("Now move every joint through its whole range of motion.")
        low, high = dict(homing), dict(homing)
        deadline = clock() + record_s
        while clock() < deadline and not stop():
            for servo_id, ticks in _read_positions(bus, ids).items():
                low[servo_id] = min(low[servo_id], ticks)
                high[servo_id] = max(high[servo_id], ticks)
            sleep(sample_period_s)
    still = [name for name, i in zip(names, ids, strict=True) if high[i] - low[i] < MIN_RANGE_TICKS]
    if still:
        raise ROSHardwareError(
            f"calibration on {port}: joint(s) {', '.join(still)} barely moved while recording "
            f"(less than {MIN_RANGE_TICKS} ticks); run again and move each joint end to end"
        )
    joints = {
        name: JointCalibration(
            servo_id=i, homing_ticks=homing[i], range_min=low[i], range_max=high[i], direction=signs.get(name, 1)
        )
        for name, i in zip(names, ids, strict=True)
    }
    calibration = ArmCalibration(robot_id=manifest.robot_id, joints=joints)
    save_calibration(calibration, output)
    say(f"Calibration written to {output}")
    return calibration


def _read_positions(bus: FeetechBus, ids: list[int]) -> dict[int, int]:
    raw = bus.sync_read(ids, Register.PRESENT_POSITION, 2)
    return {i: p.decode_sign_magnitude(p.from_u16(raw[i])) for i in ids}
