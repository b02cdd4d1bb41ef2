"""``FeetechBus``: request/reply transactions with Feetech servos over a serial port (pyserial).

Every transaction (send one request, collect the expected replies) has a deadline of
``timeout_s`` and is retried up to ``retries`` more times when a reply is missing or fails its
checksum; the input buffer is flushed before each retry so a late reply cannot be mistaken for
the next one. Serial-port failures (the adapter unplugged, the port gone) are not retried. Every
failure leaves as a ``ROSHardwareError`` naming the port, the instruction and the servo ids.
A lock serialises transactions, so an e-stop from another thread waits for the current one.
"""

from __future__ import annotations

import contextlib
import errno
import os
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Self

from openral_core.errors import ROSDependencyMissing, ROSHardwareError
from openral_hal.device_lock import device_busy_error, lock_device, unlock_device
from openral_hal.feetech import protocol as p

try:
    import serial
except ImportError as exc:
    raise ROSDependencyMissing(
        "serial", extra="serial", needed_for="the Feetech servo bus (SO-100/SO-101 arm)"
    ) from exc

DEFAULT_BAUDRATE = 1_000_000


@dataclass
class BusStats:
    """Counters of one bus since it was created.

    Attributes:
        transactions: Requests that completed (after any retries).
        retries: Extra attempts made after a timeout or a bad packet.
        timeouts: Attempts that ended with a reply missing.
        bad_packets: Replies dropped for a wrong checksum or framing.
    """

    transactions: int = 0
    retries: int = 0
    timeouts: int = 0
    bad_packets: int = 0


class _AttemptFailed(Exception):
    """One attempt of a transaction failed in a way a retry may fix."""

    def __init__(self, message: str, missing: list[int]) -> None:
        super().__init__(message)
        self.missing = missing


class ServoNoReply(ROSHardwareError):
    """A transaction got no valid reply from some servos after all its attempts.

    Attributes:
        port: The bus's serial port.
        missing: The servo ids that never answered validly.
    """

    def __init__(self, message: str, *, port: str, missing: list[int]) -> None:
        super().__init__(message)
        self.port = port
        self.missing = missing


class FeetechBus:
    """A Feetech servo bus on one serial port.

    Args:
        port: Serial device (``/dev/ttyACM0``) or a pseudo-terminal of the emulator.
        baudrate: Bus speed; STS servos ship at 1 Mbit/s.
        timeout_s: Deadline of one attempt of a transaction.
        retries: Extra attempts after a timeout or a corrupt reply (0 = try once).
        serial_factory: Builds the open port (tests inject one); default ``serial.Serial``.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        timeout_s: float = 0.02,
        retries: int = 2,
        serial_factory: Callable[..., serial.Serial] | None = None,
    ) -> None:
        if timeout_s <= 0:
            raise ValueError("timeout_s must be positive")
        if retries < 0:
            raise ValueError("retries must be >= 0")
        self.port = port
        self.baudrate = baudrate
        self.timeout_s = timeout_s
        self.retries = retries
        self.stats = BusStats()
        self._factory = serial_factory or serial.Serial
        self._serial: serial.Serial | None = None
        self._lock = threading.RLock()
        self._buffer = bytearray()

    # -- port lifecycle -------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """``True`` between ``open()`` and ``close()``."""
        return self._serial is not None

    def open(self) -> None:
        """Open the port. Opening an open bus does nothing.

        Raises:
            ROSHardwareError: The port does not exist or cannot be opened.
        """
        with self._lock:
            if self._serial is not None:
                return
            try:
                ser = self._factory(
                    self.port, baudrate=self.baudrate, timeout=self.timeout_s, write_timeout=max(self.timeout_s, 0.1)
                )
            except (serial.SerialException, OSError, ValueError) as exc:
                if getattr(exc, "errno", None) == errno.EBUSY:  # another program holds it exclusively
                    raise device_busy_error(self.port) from exc
                raise ROSHardwareError(
                    f"cannot open servo bus port {self.port} at {self.baudrate} baud: {exc} "
                    "(is the arm's USB adapter plugged in, and is the port readable by this user?)"
                ) from exc
            try:
                lock_device(ser.fileno(), self.port)
            except BaseException:
                with contextlib.suppress(serial.SerialException, OSError):
                    ser.close()
                raise
            self._serial = ser
            self._buffer.clear()

    def close(self) -> None:
        """Release and close the port. Idempotent; errors while closing a dead port are ignored."""
        with self._lock:
            ser, self._serial = self._serial, None
            if ser is not None:
                with contextlib.suppress(serial.SerialException, OSError, ValueError):
                    unlock_device(ser.fileno())
                with contextlib.suppress(serial.SerialException, OSError):
                    ser.close()

    def broadcast_now(self, packet: bytes) -> None:
        """Write ``packet`` at once, without waiting for a transaction in progress; no reply is read.

        For a broadcast that must go out even while another thread is stuck in a transaction
        (torque off on a forced stop). Never raises.
        """
        ser = self._serial
        if ser is not None:
            with contextlib.suppress(serial.SerialException, OSError, ValueError):
                os.write(ser.fileno(), packet)

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    # -- transactions -----------------------------------------------------------------------------

    def ping(self, servo_id: int) -> None:
        """Check that ``servo_id`` answers.

        Raises:
            ROSHardwareError: No valid reply after the retries, or the port failed.
        """
        self._transact(p.ping_packet(servo_id), [servo_id], 0, what=f"PING of servo {servo_id}")

    def find(self, servo_ids: Iterable[int]) -> list[int]:
        """The ids among ``servo_ids`` that do not answer a ping (empty when all are there).

        Raises:
            ROSHardwareError: The port itself failed.
        """
        missing = []
        for servo_id in servo_ids:
            try:
                self.ping(servo_id)
            except ServoNoReply:
                missing.append(servo_id)
        return missing

    def read(self, servo_id: int, address: int, length: int) -> bytes:
        """READ ``length`` bytes at ``address`` of one servo.

        Raises:
            ROSHardwareError: No valid reply after the retries, or the port failed.
        """
        replies = self._transact(
            p.read_packet(servo_id, address, length),
            [servo_id],
            length,
            what=f"READ of {length} bytes at address {address} from servo {servo_id}",
        )
        return replies[servo_id]

    def write(self, servo_id: int, address: int, data: bytes) -> None:
        """WRITE ``data`` at ``address`` of one servo and wait for its acknowledgement.

        Raises:
            ROSHardwareError: No valid reply after the retries, or the port failed.
        """
        self._transact(
            p.write_packet(servo_id, address, data),
            [servo_id],
            0,
            what=f"WRITE at address {address} of servo {servo_id}",
        )

    def sync_read(self, servo_ids: Iterable[int], address: int, length: int) -> dict[int, bytes]:
        """SYNC_READ ``length`` bytes at ``address`` from every listed servo in one request.

        Raises:
            ROSHardwareError: A servo's reply is missing or corrupt after the retries, or the port failed.
        """
        ids = list(servo_ids)
        return self._transact(
            p.sync_read_packet(ids, address, length),
            ids,
            length,
            what=f"SYNC_READ of {length} bytes at address {address}",
        )

    def sync_write(self, address: int, data: Mapping[int, bytes]) -> None:
        """SYNC_WRITE ``data[id]`` at ``address`` of every listed servo (no reply is defined).

        Raises:
            ROSHardwareError: The port failed.
        """
        packet = p.sync_write_packet(address, data)
        with self._lock:
            ser = self._require_open(f"SYNC_WRITE at address {address} to servos {sorted(data)}")
            try:
                ser.write(packet)
            except (serial.SerialException, OSError) as exc:
                self._gone(exc, f"SYNC_WRITE at address {address} to servos {sorted(data)}")
            self.stats.transactions += 1

    # -- internals ------------------------------------------------------------------------------

    def _require_open(self, what: str) -> serial.Serial:
        if self._serial is None:
            raise ROSHardwareError(f"servo bus {self.port} is not open; cannot do {what}")
        return self._serial

    def _gone(self, exc: BaseException, what: str) -> None:
        raise ROSHardwareError(
            f"servo bus {self.port} failed during {what}: {exc} (was the adapter unplugged or the arm powered off?)"
        ) from exc

    def _transact(self, packet: bytes, ids: list[int], length: int, *, what: str) -> dict[int, bytes]:
        attempts = self.retries + 1
        with self._lock:
            ser = self._require_open(what)
            last = _AttemptFailed("not attempted", ids)
            for attempt in range(attempts):
                if attempt:
                    self.stats.retries += 1
                try:
                    if attempt or self._buffer or ser.in_waiting:
                        ser.reset_input_buffer()
                        self._buffer.clear()
                    ser.write(packet)
                    replies = self._collect(ser, ids, length)
                except (serial.SerialException, OSError) as exc:
                    self._gone(exc, what)
                except _AttemptFailed as exc:
                    last = exc
                    continue
                self.stats.transactions += 1
                return replies
        raise ServoNoReply(
            f"servo bus {self.port}: {what} failed after {attempts} attempt(s) "
            f"of {self.timeout_s * 1000:.0f} ms each: {last} "
            "(check the servo's power, cable and id; a wrong baud rate looks the same)",
            port=self.port,
            missing=last.missing,
        )

    def _collect(self, ser: serial.Serial, ids: list[int], length: int) -> dict[int, bytes]:
        """Read replies until every id in ``ids`` answered with ``length`` bytes, or the deadline."""
        deadline = time.monotonic() + self.timeout_s
        wanted = set(ids)
        replies: dict[int, bytes] = {}
        buffer = self._buffer
        corrupt = False
        while wanted:
            while True:
                try:
                    packet, used = p.decode(buffer)
                except p.PacketError as exc:
                    del buffer[: exc.consumed]
                    self.stats.bad_packets += 1
                    corrupt = True
                    continue
                del buffer[:used]
                if packet is None:
                    break
                if packet.servo_id in wanted and len(packet.params) == length:
                    replies[packet.servo_id] = packet.params
                    wanted.discard(packet.servo_id)
            if not wanted:
                break
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            need = max(1, min(ser.in_waiting, 4096) or (len(wanted) * (length + 6)))
            chunk = ser.read(need)
            buffer += chunk
            if not chunk and time.monotonic() >= deadline:
                break
        if wanted:
            self.stats.timeouts += 1
            reason = "a corrupt reply (checksum mismatch) and no valid one" if corrupt else "no reply"
            missing = sorted(wanted)
            raise _AttemptFailed(f"{reason} from servo(s) {', '.join(str(i) for i in missing)}", missing)
        buffer.clear()
        return replies
