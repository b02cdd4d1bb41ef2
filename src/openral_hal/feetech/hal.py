"""``SO10xFollowerHAL``: an SO-100 / SO-101 follower arm on a Feetech STS3215 bus (pyserial).

``connect`` opens the port, pings every servo (all missing ones are named in one error), makes
each goal its present position so torque-on does not jump, and enables torque. ``read_state``
is one SYNC_READ of present position and speed (addresses 56..59) for all servos;
``send_action`` is one SYNC_WRITE of goal positions. Angles convert through the calibration
file (:mod:`openral_hal.feetech.calibration`): every joint, the jaw included, is in the
manifest's radians, and goals are clipped into both the manifest limits and the calibrated
tick range. ``estop`` makes each goal the present position (optionally then disables torque).

``emulate: true`` starts a :class:`~openral_hal.feetech.emulator.ServoBusEmulator` on a
pseudo-terminal inside ``connect`` and drives it through the same serial code: for demos and
CI without an arm, never for a real one (it ignores ``port``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from contextlib import ExitStack, suppress
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from openral_core.actions import Action
from openral_core.config import validate_model
from openral_core.errors import ROSConfigError, ROSHardwareError
from openral_core.robot import RobotManifest
from openral_core.world import JointState
from openral_hal.feetech import protocol as p
from openral_hal.feetech.bus import DEFAULT_BAUDRATE, FeetechBus, ServoNoReply
from openral_hal.feetech.calibration import ArmCalibration, load_calibration
from openral_hal.feetech.emulator import ServoBusEmulator
from openral_hal.feetech.protocol import Register
from openral_hal.joints import JointIndex

MAX_BAUDRATE = 4_000_000
"""Fastest serial rate accepted; Linux USB serial adapters top out here (STS3215 servos at 1 Mbit/s)."""


class SO10xFollowerParams(BaseModel):
    """Parameters of the ``so10x_follower`` HAL.

    Attributes:
        port: Serial device of the arm's bus adapter (``/dev/ttyACM0``); required unless ``emulate``.
        baudrate: Bus speed (STS3215 default 1 Mbit/s).
        calibration: Calibration file written by ``openral calibrate``; required unless ``emulate``
            (the emulator uses a nominal calibration built from the manifest).
        timeout_s: Deadline of one bus transaction attempt.
        retries: Extra attempts of a transaction after a timeout or a corrupt reply.
        estop_torque_off: After holding on e-stop, also disable torque (the arm goes limp).
        torque_off_on_disconnect: Disable torque when disconnecting (the arm goes limp).
        emulate: Run against an in-process emulated bus instead of ``port`` (demos and CI only).
        emulator_speed_ticks_s: Top speed of the emulated servos.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    port: str | None = None
    baudrate: int = Field(default=DEFAULT_BAUDRATE, gt=0, le=MAX_BAUDRATE)
    calibration: Path | None = None
    timeout_s: float = Field(default=0.02, gt=0, le=1.0)
    retries: int = Field(default=2, ge=0, le=10)
    estop_torque_off: bool = False
    torque_off_on_disconnect: bool = True
    emulate: bool = False
    emulator_speed_ticks_s: float = Field(default=3000.0, gt=0, le=1e6)

    @model_validator(mode="after")
    def _port_or_emulate(self) -> SO10xFollowerParams:
        if not self.emulate and (self.port is None or self.calibration is None):
            raise ValueError("'port' and 'calibration' are required unless 'emulate' is true")
        return self


class SO10xFollowerHAL:
    """The SO-100/SO-101 follower arm over its Feetech servo bus.

    Args:
        manifest: The robot; every joint needs a ``servo_id``.
        params: Validated as :class:`SO10xFollowerParams`.

    Attributes:
        bus: The open bus while connected (its ``stats`` count retries and bad packets).
        emulator: The emulated bus while connected with ``emulate: true``.

    Raises:
        ROSConfigError: A wrong parameter, an unreadable calibration file, or one that does not
            match the manifest.
    """

    adapter = "so10x_follower"
    params_model: type[SO10xFollowerParams] = SO10xFollowerParams
    field_prefix = "hal.params"

    def __init__(self, manifest: RobotManifest, params: Mapping[str, Any] | None = None) -> None:
        self.params = validate_model(
            self.params_model, dict(params or {}), source=f"the {self.adapter} arm", field_prefix=self.field_prefix
        )
        self.manifest = manifest
        self.robot_id = manifest.robot_id
        self.joint_names = manifest.joint_names
        self._index = JointIndex(self.robot_id, self.joint_names)
        if self.params.calibration is not None:
            self.calibration = load_calibration(self.params.calibration, field=f"{self.field_prefix}.calibration")
        else:
            self.calibration = ArmCalibration.from_manifest(manifest)
        self.calibration.check(manifest)
        self._cal = [self.calibration.joints[name] for name in self.joint_names]
        self._ids = [c.servo_id for c in self._cal]
        self._lower = [j.lower for j in manifest.joints]
        self._upper = [j.upper for j in manifest.joints]
        self._goals = [0] * len(self._ids)
        self._lock = threading.RLock()
        self.bus: FeetechBus | None = None
        self.emulator: ServoBusEmulator | None = None
        self._stack: ExitStack | None = None
        if len(set(self._ids)) != len(self._ids):
            raise ROSConfigError(f"robot '{self.robot_id}' repeats a servo id: {self._ids}", field="joints.servo_id")

    @property
    def is_connected(self) -> bool:
        """``True`` between ``connect()`` and ``disconnect()`` while the bus port works."""
        return self.bus is not None and self.bus.is_open

    def connect(self) -> None:
        """Open the bus, find every servo, hold the present pose and enable torque.

        Raises:
            ROSHardwareError: The port cannot be opened, servos are missing (all named), or
                configuring them failed. Nothing is left open.
        """
        with self._lock:
            if self.bus is not None:
                return
            with ExitStack() as stack:
                port = self.params.port or ""
                if self.params.emulate:
                    emulator = self._make_emulator()
                    stack.enter_context(emulator)
                    port = emulator.port
                    self.emulator = emulator
                    stack.callback(setattr, self, "emulator", None)
                bus = FeetechBus(
                    port, baudrate=self.params.baudrate, timeout_s=self.params.timeout_s, retries=self.params.retries
                )
                stack.enter_context(bus)
                missing = bus.find(self._ids)
                if missing:
                    names = [f"{self.joint_names[self._ids.index(i)]} (id {i})" for i in missing]
                    raise ROSHardwareError(
                        f"robot '{self.robot_id}' on {port}: servo(s) {', '.join(names)} did not answer a ping "
                        f"(check power, the daisy-chain cable at that joint, and the servo id)"
                    )
                self._prepare(bus)
                self._stack = stack.pop_all()
                self.bus = bus

    def disconnect(self) -> None:
        """Optionally disable torque, then close the bus (and the emulator). Idempotent; never raises.

        Safe from another thread while a transaction is stuck: the torque-off broadcast goes out
        first, without waiting for the bus.
        """
        bus = self.bus
        if bus is not None and self.params.torque_off_on_disconnect:
            # One broadcast that needs no reply and no lock, so the arm goes limp even if another
            # thread is stuck in a transaction; then, in order, acknowledged writes one per servo
            # (a broadcast gets no reply, and closing the port right after it could lose it).
            bus.broadcast_now(p.write_packet(p.BROADCAST_ID, Register.TORQUE_ENABLE, b"\x00"))
        with self._lock:
            bus, stack = self.bus, self._stack
            self.bus, self._stack = None, None
            if bus is not None and self.params.torque_off_on_disconnect:
                for servo_id in self._ids:
                    with suppress(ROSHardwareError):
                        bus.write(servo_id, Register.TORQUE_ENABLE, b"\x00")
            if stack is not None:
                stack.close()

    def read_state(self) -> JointState:
        """Present joint positions (rad) and velocities (rad/s), one SYNC_READ.

        Raises:
            ROSHardwareError: Not connected, or the read failed after its retries.
        """
        bus = self._bus()
        stamp = time.monotonic_ns()
        ticks = self._read_ticks(bus)
        positions = [c.to_radians(t) for c, (t, _) in zip(self._cal, ticks, strict=True)]
        velocities = [c.direction * s * p.RAD_PER_TICK for c, (_, s) in zip(self._cal, ticks, strict=True)]
        return JointState.model_construct(
            names=list(self.joint_names), positions=positions, velocities=velocities, efforts=None, stamp_ns=stamp
        )

    def send_action(self, action: Action) -> None:
        """Row 0 as goal positions, clipped to the limits, in one SYNC_WRITE of all joints.

        Raises:
            ROSConfigError: Unknown joint or unsupported control mode.
            ROSSafetyViolation: A non-finite value.
            ROSHardwareError: Not connected, or the write failed.
        """
        bus = self._bus()
        indices, values = self._index.targets(action, adapter=self.adapter)
        with self._lock:
            for i, value in zip(indices, values, strict=True):
                clipped = min(max(value, self._lower[i]), self._upper[i])
                self._goals[i] = self._cal[i].to_ticks(clipped)
            data = self._goal_data()
        bus.sync_write(Register.GOAL_POSITION, data)

    def estop(self) -> None:
        """Hold: goal := present position for every servo; with ``estop_torque_off`` then torque off.

        Raises:
            ROSHardwareError: Not connected, or the hold could not be delivered.
        """
        bus = self._bus()
        with self._lock:
            ticks = self._read_ticks(bus)
            self._goals = [round(t) for t, _ in ticks]
            bus.sync_write(Register.GOAL_POSITION, self._goal_data())
            if self.params.estop_torque_off:
                bus.sync_write(Register.TORQUE_ENABLE, dict.fromkeys(self._ids, b"\x00"))

    # -- internals ------------------------------------------------------------------------------

    def _make_emulator(self) -> ServoBusEmulator:
        return ServoBusEmulator(self._ids, speed_ticks_s=self.params.emulator_speed_ticks_s)

    def _prepare(self, bus: FeetechBus) -> None:
        """Hold the present pose, then enable torque (a follower must not jump when it powers up)."""
        ticks = self._read_ticks(bus)
        self._goals = [round(t) for t, _ in ticks]
        bus.sync_write(Register.GOAL_POSITION, self._goal_data())
        bus.sync_write(Register.TORQUE_ENABLE, dict.fromkeys(self._ids, b"\x01"))

    def _bus(self) -> FeetechBus:
        bus = self.bus
        if bus is None:
            raise ROSHardwareError(f"so10x_follower HAL of '{self.robot_id}' is not connected; call connect() first")
        return bus

    def _goal_data(self) -> dict[int, bytes]:
        return {i: p.u16(p.encode_sign_magnitude(g)) for i, g in zip(self._ids, self._goals, strict=True)}

    def _read_ticks(self, bus: FeetechBus) -> list[tuple[int, int]]:
        """(present position, present speed) in ticks and ticks/s per joint, in joint order."""
        try:
            raw = bus.sync_read(self._ids, Register.PRESENT_POSITION, 4)
        except ServoNoReply as exc:
            names = [self.joint_names[self._ids.index(i)] for i in exc.missing if i in self._ids]
            raise ServoNoReply(f"{exc} [joints: {', '.join(names)}]", port=exc.port, missing=exc.missing) from exc
        return [
            (p.decode_sign_magnitude(p.from_u16(raw[i])), p.decode_sign_magnitude(p.from_u16(raw[i], 2)))
            for i in self._ids
        ]
