"""LeRobot calibration files: found before anything connects, written to the motors without a prompt.

``lerobot-calibrate`` writes one JSON file per arm (``<calibration_dir>/<id>.json``; a bimanual
device has one per arm, ids suffixed ``_left``/``_right``). LeRobot's ``connect()`` asks on the
terminal whether to use the file when the motors disagree with it; a deployment must never
wait on a prompt, so openral connects with ``calibrate=False``, refuses to build a device whose
file is missing (naming the file and the command that writes it), and, when the motors hold
other values, writes the file's to them: what LeRobot does when the operator presses ENTER.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from openral_core.errors import ROSConfigError
from openral_hal.lerobot.motors import motor_buses

CalibratedKind = Literal["robot", "teleop"]
"""The prefix of LeRobot's command-line flags for the device (``--robot.type``, ``--teleop.type``)."""


def calibrate_command(kind: CalibratedKind, type_name: str, params: Mapping[str, Any]) -> str:
    """The ``lerobot-calibrate`` command line that writes this device's calibration files."""
    flags = [f"--{kind}.type={type_name}"]
    for key, value in _flatten(params):
        if key == "id" or key.endswith("port") or key == "calibration_dir":
            flags.append(f"--{kind}.{key}={value}")
    return "lerobot-calibrate " + " ".join(flags)


def require_calibration(
    device: Any, *, kind: CalibratedKind, type_name: str, params: Mapping[str, Any], field: str
) -> None:
    """Refuse a device with motors whose calibration file is missing or empty.

    Raises:
        ROSConfigError: A file is missing; names it, the ``id`` it was looked up by, and the command.
    """
    for found in motor_buses(device):
        owner = found.owner
        if owner.calibration:
            continue
        path = getattr(owner, "calibration_fpath", None)
        raise ROSConfigError(
            f"no LeRobot calibration for '{getattr(owner, 'id', None)}' at {path}",
            field=f"{field}.id" if "id" in params else f"{field}.calibration_dir",
            hint=f"calibrate the arm once with: {calibrate_command(kind, type_name, params)} "
            "(or point calibration_dir at the folder that holds the file)",
        )


def write_calibration_where_it_differs(device: Any) -> list[str]:
    """Write each arm's calibration file to its motors where they hold other values.

    Returns:
        The ids of the arms written.
    """
    written = []
    for found in motor_buses(device):
        bus, owner = found.bus, found.owner
        if not owner.calibration or bus.is_calibrated:
            continue
        with bus.torque_disabled():
            bus.write_calibration(owner.calibration)
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
