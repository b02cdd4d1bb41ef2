"""``ServoBusEmulator``: Feetech STS3215 servos answering the real protocol on a pseudo-terminal.

For tests, CI and demos without an arm. ``os.openpty()`` gives a master/slave pair; the
emulator serves the master from a daemon thread and :attr:`ServoBusEmulator.port` names the
slave device, which pyserial opens exactly like a USB adapter. Each servo has a 256-byte
control table; with torque enabled its present position moves toward the goal at a servo-like
speed (default 3000 ticks/s, about 4.6 rad/s, the STS3215's no-load speed) and reports its
present speed; with torque off it stays where it is put (:meth:`ServoBusEmulator.move_by_hand`), or, as a
leader arm moved by an operator, follows a recorded trajectory (:meth:`ServoBusEmulator.play`).

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


class EmulatedServo:
    """One STS3215: a control table plus first-order motion toward the goal.

    Attributes:
        servo_id: Bus id.
        memory: The 256-byte control table (little-endian registers).
        position: Present position in ticks (float, for smooth motion).
        speed: Present speed in ticks/s (signed).
    """

    def __init__(self, servo_id: int, position: int, speed_ticks_s: float) -> None:
        self.servo_id = servo_id
        self.memory = bytearray(256)
        self.memory[Register.MODEL_NUMBER : Register.MODEL_NUMBER + 2] = p.u16(p.STS3215_MODEL_NUMBER)
        self.memory[Register.ID] = servo_id
        self.memory[Register.MAX_POSITION_LIMIT : Register.MAX_POSITION_LIMIT + 2] = p.u16(p.MAX_TICK)
        self.memory[Register.GOAL_POSITION : Register.GOAL_POSITION + 2] = p.u16(position)
        self.max_speed = speed_ticks_s
        self.position = float(position)
        self.speed = 0.0
        self._sync_present()

    @property
    def torque_enabled(self) -> bool:
        """Torque enable register (address 40) is non-zero."""
        return bool(self.memory[Register.TORQUE_ENABLE])

    @property
    def goal(self) -> int:
        """Goal position register (address 42), ticks."""
        return p.decode_sign_magnitude(p.from_u16(self.memory, Register.GOAL_POSITION))

    def advance(self, dt: float) -> None:
        """Move toward the goal for ``dt`` seconds (only with torque on)."""
        if not self.torque_enabled or dt <= 0:
            self.speed = 0.0
        else:
            goal = min(max(self.goal, 0), p.MAX_TICK)
            error = goal - self.position
            step = min(abs(error), self.max_speed * dt)
            self.position += step if error > 0 else -step
            self.speed = (step if error > 0 else -step) / dt
        self._sync_present()

    def _sync_present(self) -> None:
        ticks = round(self.position)
        self.memory[Register.PRESENT_POSITION : Register.PRESENT_POSITION + 2] = p.u16(ticks)
        raw_speed = p.encode_sign_magnitude(max(-32767, min(32767, round(self.speed))))
        self.memory[Register.PRESENT_SPEED : Register.PRESENT_SPEED + 2] = p.u16(raw_speed)
        self.memory[Register.MOVING] = int(abs(self.speed) > 0)


class ServoBusEmulator:
    """Emulated servos on a pseudo-terminal; a context manager that starts and stops its thread.

    Args:
        servo_ids: Ids of the servos on the bus.
        initial_ticks: Start position per id (default 2048, the middle of a turn).
        speed_ticks_s: Top speed toward the goal, ticks/s.

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
    ) -> None:
        start = dict(initial_ticks or {})
        self.servos = {i: EmulatedServo(i, start.get(i, 2048), speed_ticks_s) for i in servo_ids}
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
        """Present positions in ticks by id (advanced to now)."""
        with self._lock:
            self._advance()
            return {i: round(s.position) for i, s in self.servos.items()}

    def goals(self) -> dict[int, int]:
        """Goal positions in ticks by id."""
        with self._lock:
            return {i: s.goal for i, s in self.servos.items()}

    def torque(self) -> dict[int, bool]:
        """Torque enable by id."""
        with self._lock:
            return {i: s.torque_enabled for i, s in self.servos.items()}

    def move_by_hand(self, servo_id: int, ticks: int) -> None:
        """Put a servo at ``ticks`` as a hand would (a torque-on servo then drives back to its goal)."""
        with self._lock:
            self._advance()
            servo = self.servos[servo_id]
            servo.position = float(min(max(ticks, 0), p.MAX_TICK))
            servo.advance(0.0)

    def play(self, trajectory: Sequence[tuple[float, Mapping[int, int]]], *, loop: bool = True) -> None:
        """Move the torque-off servos along ``trajectory`` (seconds from now, ticks by id), as a hand would.

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
                    servo.memory[address : address + size] = params[k + 1 : k + 1 + size]
                    servo.advance(0.0)
            return []
        if code == Instruction.SYNC_READ and len(params) >= 2:
            address, size = params[0], params[1]
            out = []
            for servo_id in params[2:]:
                servo = self._present(servo_id)
                if servo is not None:
                    out.append(p.status_packet(servo_id, 0, bytes(servo.memory[address : address + size])))
            return out
        targets = list(self.servos) if packet.servo_id == p.BROADCAST_ID else [packet.servo_id]
        out = []
        for servo_id in targets:
            servo = self._present(servo_id)
            if servo is None:
                continue
            data = b""
            if code == Instruction.READ and len(params) == 2:
                data = bytes(servo.memory[params[0] : params[0] + params[1]])
            elif code == Instruction.WRITE and params:
                servo.memory[params[0] : params[0] + len(params) - 1] = params[1:]
                servo.advance(0.0)
            elif code != Instruction.PING:
                continue
            if packet.servo_id != p.BROADCAST_ID:
                out.append(p.status_packet(servo_id, 0, data))
        return out

    def _present(self, servo_id: int) -> EmulatedServo | None:
        if servo_id in self.missing_ids:
            return None
        return self.servos.get(servo_id)
