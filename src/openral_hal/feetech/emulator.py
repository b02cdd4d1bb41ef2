"""``ServoBusEmulator``: Feetech STS3215 servos answering the real protocol on a pseudo-terminal.

For tests, CI and demos without an arm. ``os.openpty()`` gives a master/slave pair; the
emulator serves the master from a daemon thread and :attr:`ServoBusEmulator.port` names the
slave device, which pyserial (or Feetech's ``scservo_sdk``, as LeRobot's driver uses it) opens
exactly like a USB adapter. Each servo has a 256-byte control table holding the STS3215's
factory values (:data:`FACTORY_REGISTERS`); with torque enabled its present position moves
toward the goal at a servo-like speed (default 3000 ticks/s, about 4.6 rad/s, the STS3215's
no-load speed) and reports its present speed; with torque off it stays where it is put
(:meth:`ServoBusEmulator.move_by_hand`), or, as a leader arm moved by an operator, follows a
recorded trajectory (:meth:`ServoBusEmulator.play`).

What the servo does with its registers, as on the STS3215:

* Present_Position is the encoder reading less Homing_Offset (sign bit 11), wrapped into the
  turn 0..4095 (Phase bit 4 clear, single-turn feedback); with Phase bit 4 set (full-angle
  feedback) it is not wrapped and counts whole turns, so it can leave 0..4095 (sign bit 15).
  Goal_Position is in the same offset frame.
* In position mode (Operating_Mode 0) the goal is clamped into [Min_Position_Limit,
  Max_Position_Limit] and the servo drives its present position toward it within the turn: it
  never crosses the 0/4095 seam. Both limits 0 is the multi-turn mode of the memory table: no
  clamp, and the goal is an absolute position over several turns. Other modes hold still.
* Writes to EEPROM (addresses 5..39) take effect at once; with Lock 0 they are also kept over
  :meth:`ServoBusEmulator.power_cycle`, with Lock 1 they are lost there. Lock powers up 0. The
  read-only version and feedback bytes ignore writes. Writing ID moves the servo to the new id
  (one another servo has is undone: the emulator holds one servo per id).
* Response_Status_Level 0 answers only READ and PING. A broadcast PING (id 0xFE) is answered by
  every servo, in id order; other broadcasts are executed and answered by none.

Torque on drives to the Goal_Position register as it stands (at power-on: the present position),
so a client that moved the goal, or a hand that moved a torque-off servo, sees it travel.
Not modelled: baud rate and return delay (the pty carries any), acceleration ramps, PID
dynamics, load, current and the protections.

Faults are injected by assigning attributes while it runs: ``drop_replies`` (ignore the next N
requests, so the client times out), ``corrupt_checksum`` (spoil the checksum of the next N
replies), ``missing_ids`` (servos that never answer), ``reply_delay_s`` (answer late), ``mute``
(servos execute every request but no reply reaches the client: a broken reply line), and
:meth:`ServoBusEmulator.disconnect` (the bus disappears: the master side is closed).
``on_request`` is called with every decoded request before it is executed, so a test can act at
an exact moment of the protocol (the instant torque goes on, say).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterable, Mapping, Sequence
from types import TracebackType
from typing import Self

from openral_hal.feetech import protocol as p
from openral_hal.feetech.protocol import Instruction, Register

_POLL_S = 0.005
_JOIN_TIMEOUT_S = 2.0
_EEPROM = range(Register.ID, Register.TORQUE_ENABLE)
_READ_ONLY = (range(Register.ID), range(Register.PRESENT_POSITION, Register.PRESENT_CURRENT + 2))
_MAX_MAGNITUDE = (1 << 15) - 1

FACTORY_REGISTERS: dict[Register, int] = {
    Register.FIRMWARE_MAJOR_VERSION: 3,
    Register.FIRMWARE_MINOR_VERSION: 10,
    Register.MODEL_NUMBER: p.STS3215_MODEL_NUMBER,
    Register.BAUD_RATE: 0,
    Register.RETURN_DELAY: 250,
    Register.RESPONSE_STATUS_LEVEL: 1,
    Register.MIN_POSITION_LIMIT: 0,
    Register.MAX_POSITION_LIMIT: p.MAX_TICK,
    Register.MAX_TEMPERATURE_LIMIT: 70,
    Register.MAX_VOLTAGE_LIMIT: 80,
    Register.MIN_VOLTAGE_LIMIT: 40,
    Register.MAX_TORQUE_LIMIT: 1000,
    Register.PHASE: 0x0C,
    Register.UNLOADING_CONDITION: 44,
    Register.LED_ALARM_CONDITION: 47,
    Register.P_COEFFICIENT: 32,
    Register.D_COEFFICIENT: 32,
    Register.I_COEFFICIENT: 0,
    Register.MINIMUM_STARTUP_FORCE: 16,
    Register.CW_DEAD_ZONE: 1,
    Register.CCW_DEAD_ZONE: 1,
    Register.PROTECTION_CURRENT: 500,
    Register.ANGULAR_RESOLUTION: 1,
    Register.HOMING_OFFSET: 0,
    Register.OPERATING_MODE: 0,
    Register.PROTECTIVE_TORQUE: 20,
    Register.PROTECTION_TIME: 200,
    Register.OVERLOAD_TORQUE: 80,
    Register.ACCELERATION: 0,
    Register.LOCK: 0,
    Register.PRESENT_VOLTAGE: 74,
    Register.PRESENT_TEMPERATURE: 30,
    Register.MAXIMUM_ACCELERATION: 0,
}
"""An STS3215 as it leaves the factory (the id aside), value per register.

Sources: Feetech's SMS/STS memory table (the "Magnetic Encoder STS Servo" memory table, as
Feetech's distributors publish it): baud rate 0 = 1 Mbit/s, response level 1, angle limits 0 and
4095 (both 0 = multi-turn), temperature limit 70 C, and the Phase bits (bit 2: speed in steps/s,
bit 3: speed 0 = top speed, bit 4 clear: single-turn feedback). LeRobot's ``lerobot.motors.feetech``
and robots: model number 777, firmware 3.10 (the version LeRobot's users report the SO-101
needs), Return_Delay_Time 250 = 500 us (``configure_motors``), P/D/I 32/32/0 (the defaults
LeKiwi's ``configure`` names). The protection values (voltage limits of the 7.4 V STS3215-C001,
torque limit 1000 = 100 %, protection current, overload and protective torque, alarm conditions)
are plausible STS3215 values the emulator reads back but does not act on. Maximum_Acceleration
lies in the factory area the memory table does not publish: 0 here. The present voltage and
temperature are an idle servo on a 7.4 V supply.
"""


class EmulatedServo:
    """One STS3215: a control table plus first-order motion toward the goal.

    Args:
        servo_id: Bus id.
        position: Encoder reading at power-on, ticks (the shaft's angle, before any homing offset).
        speed_ticks_s: Top speed toward the goal.
        registers: Values that replace the factory ones (a servo configured earlier), kept in EEPROM.

    Attributes:
        servo_id: Bus id.
        memory: The 256-byte control table (little-endian registers).
        position: Shaft angle in encoder ticks, counting whole turns (float, for smooth motion).
        speed: Present speed in ticks/s (signed).
    """

    def __init__(
        self,
        servo_id: int,
        position: int,
        speed_ticks_s: float,
        registers: Mapping[Register, int] | None = None,
    ) -> None:
        self.servo_id = servo_id
        self.memory = bytearray(256)
        for register, value in {**FACTORY_REGISTERS, Register.ID: servo_id, **(registers or {})}.items():
            self.set_register(register, value)
        self.max_speed = speed_ticks_s
        self.position = float(position)
        self.speed = 0.0
        self._saved = bytearray(self.memory[_EEPROM.start : _EEPROM.stop])
        self.power_on()

    # -- registers ------------------------------------------------------------------------------

    def register(self, register: Register) -> int:
        """The decoded value of ``register``."""
        size = p.register_size(register)
        return p.decode_register(register, self.memory[register : register + size])

    def set_register(self, register: Register, value: int) -> None:
        """Store ``value`` in ``register`` directly (no write rules, nothing persisted)."""
        self.memory[register : register + p.register_size(register)] = p.encode_register(register, value)

    def write(self, address: int, data: bytes) -> None:
        """A WRITE from the bus: read-only bytes are ignored, EEPROM bytes are also saved while Lock is 0."""
        save = self.memory[Register.LOCK] == 0
        for offset, byte in enumerate(data):
            at = address + offset
            if at < len(self.memory) and not any(at in block for block in _READ_ONLY):
                self.memory[at] = byte
                if save and at in _EEPROM:
                    self._saved[at - _EEPROM.start] = byte
        self.advance(0.0)

    def keep_id(self) -> None:
        """Undo a write of the ID register (in SRAM and in the saved EEPROM)."""
        self.memory[Register.ID] = self._saved[Register.ID - _EEPROM.start] = self.servo_id

    def power_on(self) -> None:
        """Reload EEPROM as saved, SRAM as at power-on; the shaft keeps its angle, not its turn count."""
        self.memory[_EEPROM.start : _EEPROM.stop] = self._saved
        self.position %= p.TICKS_PER_REV
        self.speed = 0.0
        for register in (Register.TORQUE_ENABLE, Register.GOAL_TIME, Register.GOAL_SPEED, Register.LOCK):
            self.set_register(register, 0)
        self.set_register(Register.ACCELERATION, FACTORY_REGISTERS[Register.ACCELERATION])
        self.set_register(Register.TORQUE_LIMIT, self.register(Register.MAX_TORQUE_LIMIT))
        self.set_register(Register.GOAL_POSITION, self.present)
        self._sync_present()

    # -- state ----------------------------------------------------------------------------------

    @property
    def torque_enabled(self) -> bool:
        """Torque enable register (address 40) is non-zero."""
        return bool(self.memory[Register.TORQUE_ENABLE])

    @property
    def goal(self) -> int:
        """Goal position register (address 42), ticks in the offset frame."""
        return self.register(Register.GOAL_POSITION)

    @property
    def encoder(self) -> int:
        """The magnetic encoder's reading, 0..4095."""
        return round(self.position) % p.TICKS_PER_REV

    @property
    def multi_turn(self) -> bool:
        """Both position limits are 0: the memory table's multi-turn position mode."""
        return self.register(Register.MIN_POSITION_LIMIT) == 0 == self.register(Register.MAX_POSITION_LIMIT)

    @property
    def present(self) -> int:
        """Present_Position: the shaft less the homing offset, wrapped into one turn unless Phase bit 4."""
        unwrapped = round(self.position) - self.register(Register.HOMING_OFFSET)
        if self.memory[Register.PHASE] & 0x10:
            return max(-_MAX_MAGNITUDE, min(_MAX_MAGNITUDE, unwrapped))
        return unwrapped % p.TICKS_PER_REV

    @property
    def target(self) -> int:
        """Where position mode drives to: the goal, clamped into the position limits (none in multi-turn)."""
        if self.multi_turn:
            return self.goal
        low, high = self.register(Register.MIN_POSITION_LIMIT), self.register(Register.MAX_POSITION_LIMIT)
        return min(max(self.goal, low), high)

    def advance(self, dt: float) -> None:
        """Move toward the target for ``dt`` seconds (only with torque on, in position mode)."""
        if not self.torque_enabled or dt <= 0 or self.memory[Register.OPERATING_MODE] != 0:
            self.speed = 0.0
        else:
            offset = self.register(Register.HOMING_OFFSET)
            unwrapped = self.position - offset
            if self.multi_turn or self.memory[Register.PHASE] & 0x10:
                error = self.target - unwrapped
            else:  # within the turn: the present reading, with its fraction, never crossing the seam
                error = self.target - unwrapped % p.TICKS_PER_REV
            step = min(abs(error), self.max_speed * dt)
            self.position += step if error > 0 else -step
            self.speed = (step if error > 0 else -step) / dt
        self._sync_present()

    def _sync_present(self) -> None:
        self.set_register(Register.PRESENT_POSITION, self.present)
        self.set_register(Register.PRESENT_SPEED, max(-_MAX_MAGNITUDE, min(_MAX_MAGNITUDE, round(self.speed))))
        self.memory[Register.MOVING] = int(abs(self.speed) > 0)


class ServoBusEmulator:
    """Emulated servos on a pseudo-terminal; a context manager that starts and stops its thread.

    Args:
        servo_ids: Ids of the servos on the bus.
        initial_ticks: Encoder reading at start per id (default 2048, the middle of a turn).
        speed_ticks_s: Top speed toward the goal, ticks/s.
        registers: Register values per id that replace the factory ones, as on servos configured
            earlier (a calibrated arm: Homing_Offset and the position limits); the goal starts at
            the present position.

    Attributes:
        port: Path of the pty slave to open with pyserial (valid after ``start()``).
        servos: The emulated servos by id.
        requests: Requests received (valid or not), for assertions.
    """

    def __init__(
        self,
        servo_ids: Iterable[int],
        *,
        initial_ticks: Mapping[int, int] | None = None,
        speed_ticks_s: float = 3000.0,
        registers: Mapping[int, Mapping[Register, int]] | None = None,
    ) -> None:
        start = dict(initial_ticks or {})
        preset = dict(registers or {})
        self.servos = {i: EmulatedServo(i, start.get(i, 2048), speed_ticks_s, preset.get(i)) for i in sorted(servo_ids)}
        self.drop_replies = 0
        self.corrupt_checksum = 0
        self.missing_ids: set[int] = set()
        self.reply_delay_s = 0.0
        self.mute = False
        self.on_request: Callable[[p.Packet], None] | None = None
        self.requests = 0
        self.port = ""
        self._master = -1
        self._slave = -1
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._gone = threading.Event()
        self._thread: threading.Thread | None = None
        self._last = time.monotonic()
        self._trajectory: list[tuple[float, dict[int, int]]] = []
        self._loop = True
        self._played_from = 0.0

    # -- lifecycle --------------------------------------------------------------------------------

    def start(self) -> Self:
        """Open the pty pair and start serving. Starting a running emulator does nothing."""
        if self._thread is not None:
            return self
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._stop.clear()
        self._gone.clear()
        self._last = time.monotonic()
        self._thread = threading.Thread(target=self._serve, name="servo-bus-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the pty. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(_JOIN_TIMEOUT_S)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1

    def disconnect(self) -> None:
        """Make the bus vanish mid-run (adapter unplugged): the pty's master side is closed.

        Afterwards the client's reads and writes on :attr:`port` fail.
        """
        self._gone.set()
        if self._thread is not None:
            self._thread.join(_JOIN_TIMEOUT_S)
            self._thread = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.stop()

    # -- state for tests and demos --------------------------------------------------------------

    def positions(self) -> dict[int, int]:
        """Present positions in ticks by id (advanced to now), as the servos report them."""
        with self._lock:
            self._advance()
            return {i: s.present for i, s in self.servos.items()}

    def encoders(self) -> dict[int, int]:
        """Encoder readings in ticks by id (advanced to now): the shafts' angles, before any homing offset."""
        with self._lock:
            self._advance()
            return {i: s.encoder for i, s in self.servos.items()}

    def goals(self) -> dict[int, int]:
        """Goal position registers in ticks by id (the homing-offset frame of the present position)."""
        with self._lock:
            return {i: s.goal for i, s in self.servos.items()}

    def torque(self) -> dict[int, bool]:
        """Torque enable by id."""
        with self._lock:
            return {i: s.torque_enabled for i, s in self.servos.items()}

    def move_by_hand(self, servo_id: int, ticks: int) -> None:
        """Turn a servo's shaft to encoder reading ``ticks`` as a hand would (a torque-on servo then drives back)."""
        with self._lock:
            self._advance()
            servo = self.servos[servo_id]
            servo.position = float(min(max(ticks, 0), p.MAX_TICK))
            servo.advance(0.0)

    def power_cycle(self) -> None:
        """Switch the servos off and on: EEPROM as last saved under Lock 0, SRAM as at power-on (torque off)."""
        with self._lock:
            self._advance()
            for servo in list(self.servos.values()):
                servo.power_on()
                self._follow_id(servo)

    def play(self, trajectory: Sequence[tuple[float, Mapping[int, int]]], *, loop: bool = True) -> None:
        """Move the torque-off servos along ``trajectory`` (seconds from now, encoder ticks by id), as a hand would.

        Positions are interpolated linearly between samples; after the last one the trajectory
        starts again (``loop``) or stays at its end. A torque-on servo keeps driving to its goal.

        Raises:
            ValueError: An empty trajectory, or times that do not increase.
        """
        samples = [(float(t), dict(ticks)) for t, ticks in trajectory]
        if not samples or any(b[0] <= a[0] for a, b in itertools.pairwise(samples)):
            raise ValueError("a trajectory needs samples at increasing times")
        with self._lock:
            self._trajectory = samples
            self._loop = loop
            self._played_from = time.monotonic()

    # -- serving --------------------------------------------------------------------------------

    def _advance(self) -> None:
        now = time.monotonic()
        dt, self._last = now - self._last, now
        for servo in self.servos.values():
            servo.advance(dt)
        if self._trajectory:
            self._follow_trajectory(now - self._played_from)

    def _follow_trajectory(self, elapsed: float) -> None:
        samples = self._trajectory
        end = samples[-1][0]
        at = samples[0][0] + (elapsed % end if self._loop and end > 0 else min(elapsed, end))
        after = next((i for i, (t, _) in enumerate(samples) if t >= at), len(samples) - 1)
        before = max(0, after - 1)
        (t0, a), (t1, b) = samples[before], samples[after]
        weight = 0.0 if t1 <= t0 else (at - t0) / (t1 - t0)
        for servo_id, servo in self.servos.items():
            if servo.torque_enabled or servo_id not in a or servo_id not in b:
                continue
            servo.position = float(a[servo_id] + weight * (b[servo_id] - a[servo_id]))
            servo.advance(0.0)

    def _serve(self) -> None:
        buffer = bytearray()
        master = self._master
        try:
            while not self._stop.is_set() and not self._gone.is_set():
                ready, _, _ = select.select([master], [], [], _POLL_S)
                if not ready:
                    continue
                try:
                    chunk = os.read(master, 4096)
                except BlockingIOError:
                    continue
                except OSError:
                    return
                buffer += chunk
                while buffer:
                    try:
                        packet, used = p.decode(buffer)
                    except p.PacketError as exc:
                        del buffer[: exc.consumed]
                        continue
                    del buffer[:used]
                    if packet is None:
                        break
                    self._handle(master, packet)
        finally:
            if self._gone.is_set():
                os.close(master)
                self._master = -1

    def _handle(self, master: int, packet: p.Packet) -> None:
        self.requests += 1
        if self.on_request is not None:
            self.on_request(packet)
        if self.drop_replies > 0:
            self.drop_replies -= 1
            return
        with self._lock:
            self._advance()
            replies = self._execute(packet)
        if not replies or self.mute:
            return
        if self.reply_delay_s > 0:
            time.sleep(self.reply_delay_s)
        out = bytearray()
        for reply in replies:
            out += reply
            if self.corrupt_checksum > 0:
                self.corrupt_checksum -= 1
                out[-1] = (out[-1] + 1) & 0xFF
        with contextlib.suppress(OSError):
            os.write(master, out)

    def _execute(self, packet: p.Packet) -> list[bytes]:
        """Apply one request; return the status replies to send."""
        code, params = packet.code, packet.params
        if code == Instruction.SYNC_WRITE and len(params) >= 2:
            address, size = params[0], params[1]
            for k in range(2, len(params) - size, size + 1):
                servo = self._present(params[k])
                if servo is not None:
                    servo.write(address, params[k + 1 : k + 1 + size])
                    self._follow_id(servo)
            return []
        if code == Instruction.SYNC_READ and len(params) >= 2:
            address, size = params[0], params[1]
            out = []
            for servo_id in params[2:]:
                servo = self._present(servo_id)
                if servo is not None:
                    out.append(p.status_packet(servo_id, 0, bytes(servo.memory[address : address + size])))
            return out
        broadcast = packet.servo_id == p.BROADCAST_ID
        targets = sorted(self.servos) if broadcast else [packet.servo_id]
        out = []
        for servo_id in targets:
            servo = self._present(servo_id)
            if servo is None:
                continue
            data = b""
            if code == Instruction.READ and len(params) == 2:
                data = bytes(servo.memory[params[0] : params[0] + params[1]])
            elif code == Instruction.WRITE and params:
                servo.write(params[0], params[1:])
                self._follow_id(servo)
            elif code != Instruction.PING:
                continue
            answers = code in (Instruction.READ, Instruction.PING) or servo.memory[Register.RESPONSE_STATUS_LEVEL]
            if answers and (not broadcast or code == Instruction.PING):
                out.append(p.status_packet(servo_id, 0, data))  # a new ID answers from the old one
        return out

    def _follow_id(self, servo: EmulatedServo) -> None:
        """A servo whose ID register was written answers at the new id; an id in use or out of range is undone."""
        new_id = servo.memory[Register.ID]
        if new_id == servo.servo_id:
            return
        if new_id > p.MAX_ID or new_id in self.servos:
            servo.keep_id()
            return
        del self.servos[servo.servo_id]
        servo.servo_id = new_id
        self.servos = dict(sorted({**self.servos, new_id: servo}.items()))

    def _present(self, servo_id: int) -> EmulatedServo | None:
        if servo_id in self.missing_ids:
            return None
        return self.servos.get(servo_id)
