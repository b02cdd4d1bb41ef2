"""The motor buses inside a LeRobot robot or teleoperator, and each motor's unit convention.

A LeRobot arm holds its motors on ``bus`` (a ``MotorsBus``: Feetech, Dynamixel, ...); a
bimanual one holds two arms as ``left_arm`` and ``right_arm`` and prefixes their keys with
``left_``/``right_``. Walking that tree gives, without connecting, the serial ports to lock,
the buses to switch torque off on, and each ``<motor>.pos`` key's ``MotorNormMode``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from openral_hal.lerobot.units import MOTOR_NORMS, MotorNorm

POSITION_SUFFIX = ".pos"
"""LeRobot's key for a motor's position: ``<motor>.pos`` in observations and actions."""

_ARMS = (("left_arm", "left_"), ("right_arm", "right_"))


@dataclass(frozen=True)
class MotorBus:
    """One bus of a device: its key prefix (``left_`` in a bimanual device, else empty) and the bus."""

    prefix: str
    bus: Any
    owner: Any
    """The (sub-)device that holds the bus: the one whose calibration file it uses."""

    @property
    def port(self) -> str:
        """The bus's serial port."""
        return str(self.bus.port)


def motor_buses(device: Any, prefix: str = "") -> Iterator[MotorBus]:
    """Every motor bus of ``device``, its arms' included, in key order."""
    bus = getattr(device, "bus", None)
    if bus is not None and hasattr(bus, "motors"):
        yield MotorBus(prefix, bus, device)
    for attribute, arm_prefix in _ARMS:
        arm = getattr(device, attribute, None)
        if arm is not None:
            yield from motor_buses(arm, prefix + arm_prefix)


def position_norms(device: Any) -> dict[str, MotorNorm]:
    """``<prefix><motor>.pos`` → the motor's LeRobot convention, for every motor on the device's buses."""
    norms: dict[str, MotorNorm] = {}
    for found in motor_buses(device):
        for name, motor in found.bus.motors.items():
            mode = str(getattr(motor.norm_mode, "value", motor.norm_mode))
            if mode in MOTOR_NORMS:
                norms[f"{found.prefix}{name}{POSITION_SUFFIX}"] = mode  # type: ignore[assignment]
    return norms
