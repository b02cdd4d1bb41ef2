"""LeRobot calibration files: found before anything connects, written to the motors without a prompt.

``lerobot-calibrate`` writes one JSON file per arm (``<calibration_dir>/<id>.json``; a bimanual
device has one per arm, ids suffixed ``_left``/``_right``). LeRobot's ``connect()`` asks on the
terminal whether to use the file when the motors disagree with it; a deployment must never
wait on a prompt, so openral connects with ``calibrate=False``, refuses to build a device whose
file is missing (naming the file and the command that writes it), and, when the motors hold
other values, writes the file's to them: what LeRobot does when the operator presses ENTER.
"""

from __future__ import annotations

import shlex
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from openral_core.errors import ROSConfigError
from openral_hal.lerobot.motors import motor_buses

CalibratedKind = Literal["robot", "teleop"]
"""The prefix of LeRobot's command-line flags for the device (``--robot.type``, ``--teleop.type``)."""


def calibrate_command(kind: CalibratedKind, type_name: str, params: Mapping[str, Any]) -> str:
    """The ``lerobot-calibrate`` command line that writes this device's calibration files."""
    flags = [f"--{kind}.type={shlex.quote(type_name)}"]
    for key, value in _flatten(params):
        if key == "id" or key.endswith("port") or key == "calibration_dir":
            flags.append(f"--{kind}.{key}={shlex.quote(str(value))}")
    return "lerobot-calibrate " + " ".join(flags)


def require_calibration(
    device: Any, *, kind: CalibratedKind, type_name: str, params: Mapping[str, Any], field: str
) -> None:
    """Refuse a device with a motor bus whose calibration file is missing or calibrates other motors.

    Raises:
        ROSConfigError: Names the file, the arm, and the command that writes the file.
    """
    hint = (
        f"calibrate it once with: {calibrate_command(kind, type_name, params)} (or point calibration_dir at its folder)"
    )
    where = f"{field}.id" if "id" in params else f"{field}.calibration_dir"
    for found in motor_buses(device):
        path = getattr(found.owner, "calibration_fpath", None)
        if path is None:
            continue
        arm = f"{found.prefix.rstrip('_')} arm's " if found.prefix else ""
        if not Path(path).is_file():
            raise ROSConfigError(f"no LeRobot calibration file {path} for the {arm}motors", field=where, hint=hint)
        calibrated, motors = sorted(found.owner.calibration), sorted(found.bus.motors)
        if calibrated != motors:
            raise ROSConfigError(
                f"the calibration file {path} calibrates motors {calibrated}; the {arm}motors are {motors}",
                field=where,
                hint=hint,
            )


def write_calibration_where_it_differs(device: Any) -> list[str]:
    """Write each arm's calibration file to its motors where they hold other values.

    Torque is off while the limits and offsets are written (the servos lock them otherwise) and
    comes back on only where it was on: a leader arm stays limp, a follower holds.

    Returns:
        The ids of the arms written.
    """
    written = []
    for found in motor_buses(device):
        bus, owner = found.bus, found.owner
        if not getattr(owner, "calibration", None) or bus.is_calibrated:
            continue
        holding = [motor for motor, on in bus.sync_read("Torque_Enable", normalize=False).items() if on]
        bus.disable_torque()
        bus.write_calibration(owner.calibration)
        if holding:
            bus.enable_torque(holding)
        written.append(str(getattr(owner, "id", found.port)))
    return written


def _flatten(params: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for key, value in params.items():
        if isinstance(value, Mapping):
            out.extend(_flatten(value, f"{prefix}{key}."))
        elif value is not None:
            out.append((f"{prefix}{key}", value))
    return out
