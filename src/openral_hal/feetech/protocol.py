"""Feetech SCS/STS serial protocol: packet framing, checksum and the STS3215 control table.

Pure Python, no I/O. Every packet, in both directions, is framed the same way::

    0xFF 0xFF  ID  LEN  CODE  PARAM...  CHECKSUM

``LEN`` counts ``CODE``, the parameters and the checksum (``len(params) + 2``). ``CODE`` is the
instruction in a request and the servo's error byte in a status reply. The checksum is
``~(ID + LEN + CODE + sum(params)) & 0xFF``. Multi-byte registers are little-endian; the STS
series stores signed registers in sign-magnitude (:data:`SIGN_BITS`: bit 15 for positions and
speeds, bit 11 for the homing offset, bit 10 for the load). A request to ``BROADCAST_ID`` is
executed by every servo and answered by none, except PING, which every servo answers.

Sources: Feetech's SCServo SDK (``scservo_sdk``: instruction codes, SYNC_READ/SYNC_WRITE layout,
error bits), Feetech's SMS/STS memory table (the "Magnetic Encoder STS Servo" memory table:
addresses, sizes, the meaning of the Phase and Lock bytes) and LeRobot's ``STS_SMS_SERIES_CONTROL_TABLE``
and ``STS_SMS_SERIES_ENCODINGS_TABLE`` (``lerobot.motors.feetech.tables``), whose register names
:class:`Register` follows.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import IntEnum, IntFlag

HEADER = b"\xff\xff"
BROADCAST_ID = 0xFE
MAX_ID = 0xFD
STS3215_MODEL_NUMBER = 777
TICKS_PER_REV = 4096
MAX_TICK = TICKS_PER_REV - 1
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
MAX_PACKET_PARAMS = 250


class Instruction(IntEnum):
    """Instruction codes of a request packet."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83


class ServoError(IntFlag):
    """Bits of the error byte in a status reply (scservo_sdk ``ERRBIT_*``)."""

    VOLTAGE = 0x01
    ANGLE = 0x02
    OVERHEAT = 0x04
    OVERCURRENT = 0x08
    OVERLOAD = 0x20


class Register(IntEnum):
    """STS3215 (SMS/STS series) control table addresses (one byte unless marked).

    0..4 are read-only version bytes, 5..39 EEPROM configuration, 40..55 SRAM control, 56..70
    read-only SRAM feedback, 80.. factory parameters.
    """

    FIRMWARE_MAJOR_VERSION = 0  # read-only
    FIRMWARE_MINOR_VERSION = 1  # read-only
    MODEL_NUMBER = 3  # 2 bytes, read-only ("servo main/sub version")
    ID = 5  # EEPROM from here
    BAUD_RATE = 6
    RETURN_DELAY = 7  # Return_Delay_Time, 2 us units
    RESPONSE_STATUS_LEVEL = 8  # 0: only READ and PING are answered
    MIN_POSITION_LIMIT = 9  # 2 bytes
    MAX_POSITION_LIMIT = 11  # 2 bytes
    MAX_TEMPERATURE_LIMIT = 13
    MAX_VOLTAGE_LIMIT = 14  # 0.1 V
    MIN_VOLTAGE_LIMIT = 15  # 0.1 V
    MAX_TORQUE_LIMIT = 16  # 2 bytes, 0.1 %
    PHASE = 18  # bit 4: 0 single-turn position feedback, 1 full-angle feedback
    UNLOADING_CONDITION = 19
    LED_ALARM_CONDITION = 20
    P_COEFFICIENT = 21
    D_COEFFICIENT = 22
    I_COEFFICIENT = 23
    MINIMUM_STARTUP_FORCE = 24  # 2 bytes
    CW_DEAD_ZONE = 26
    CCW_DEAD_ZONE = 27
    PROTECTION_CURRENT = 28  # 2 bytes, 6.5 mA
    ANGULAR_RESOLUTION = 30
    HOMING_OFFSET = 31  # 2 bytes, sign bit 11 (the datasheet's "position correction")
    OPERATING_MODE = 33  # 0 position, 1 velocity, 2 PWM, 3 step
    PROTECTIVE_TORQUE = 34
    PROTECTION_TIME = 35
    OVERLOAD_TORQUE = 36
    TORQUE_ENABLE = 40  # SRAM from here
    ACCELERATION = 41
    GOAL_POSITION = 42  # 2 bytes, sign bit 15
    GOAL_TIME = 44  # 2 bytes
    GOAL_SPEED = 46  # 2 bytes, sign bit 15
    TORQUE_LIMIT = 48  # 2 bytes
    LOCK = 55  # 0: EEPROM writes are kept over a power cycle; 1: they are not
    PRESENT_POSITION = 56  # 2 bytes, sign bit 15
    PRESENT_SPEED = 58  # 2 bytes, sign bit 15, ticks/s
    PRESENT_LOAD = 60  # 2 bytes, sign bit 10
    PRESENT_VOLTAGE = 62  # 0.1 V
    PRESENT_TEMPERATURE = 63
    STATUS = 65
    MOVING = 66
    PRESENT_CURRENT = 69  # 2 bytes
    MAXIMUM_ACCELERATION = 85  # factory area


WORD_REGISTERS = frozenset(
    {
        Register.MODEL_NUMBER,
        Register.MIN_POSITION_LIMIT,
        Register.MAX_POSITION_LIMIT,
        Register.MAX_TORQUE_LIMIT,
        Register.MINIMUM_STARTUP_FORCE,
        Register.PROTECTION_CURRENT,
        Register.HOMING_OFFSET,
        Register.GOAL_POSITION,
        Register.GOAL_TIME,
        Register.GOAL_SPEED,
        Register.TORQUE_LIMIT,
        Register.PRESENT_POSITION,
        Register.PRESENT_SPEED,
        Register.PRESENT_LOAD,
        Register.PRESENT_CURRENT,
    }
)
"""The two-byte registers; every other :class:`Register` is one byte."""

SIGN_BITS: dict[Register, int] = {
    Register.HOMING_OFFSET: 11,
    Register.GOAL_POSITION: 15,
    Register.GOAL_SPEED: 15,
    Register.PRESENT_POSITION: 15,
    Register.PRESENT_SPEED: 15,
    Register.PRESENT_LOAD: 10,
}
"""Sign-magnitude registers and their sign bit (LeRobot's ``STS_SMS_SERIES_ENCODINGS_TABLE``)."""


def register_size(register: Register) -> int:
    """Bytes the register occupies (1 or 2)."""
    return 2 if register in WORD_REGISTERS else 1


def encode_register(register: Register, value: int) -> bytes:
    """The bytes to write for ``value`` (sign-magnitude where the register is signed).

    Raises:
        ValueError: The value does not fit the register.
    """
    size = register_size(register)
    sign_bit = SIGN_BITS.get(register)
    fits = abs(value) < 1 << sign_bit if sign_bit is not None else 0 <= value < 1 << (8 * size)
    if not fits:
        raise ValueError(f"{value} does not fit the {size}-byte register {register.name}")
    raw = encode_sign_magnitude(value, sign_bit) if sign_bit is not None else value
    return u16(raw) if size == 2 else bytes((raw,))


def decode_register(register: Register, data: bytes | bytearray) -> int:
    """The value of ``register`` from the bytes read at its address (inverse of :func:`encode_register`)."""
    raw = from_u16(data) if register_size(register) == 2 else data[0]
    return decode_sign_magnitude(raw, SIGN_BITS[register]) if register in SIGN_BITS else raw


class PacketError(Exception):
    """A framed packet that cannot be accepted.

    Attributes:
        consumed: Bytes of the buffer the bad packet occupied (skip them and parse on).
    """

    def __init__(self, message: str, consumed: int) -> None:
        super().__init__(message)
        self.consumed = consumed


class ChecksumError(PacketError):
    """A packet whose checksum does not match its contents."""


@dataclass(frozen=True, slots=True)
class Packet:
    """One decoded packet.

    Attributes:
        servo_id: The addressed servo (request) or the replying one (status).
        code: The instruction (request) or the error byte (status reply).
        params: The parameter bytes.
    """

    servo_id: int
    code: int
    params: bytes

    @property
    def error(self) -> ServoError:
        """The error byte of a status reply as flags."""
        return ServoError(self.code & 0x2F)


def checksum(body: Iterable[int]) -> int:
    """``~sum(body) & 0xFF`` over the bytes from ID to the last parameter."""
    return ~sum(body) & 0xFF


def encode(servo_id: int, code: int, params: bytes | bytearray = b"") -> bytes:
    """Frame one packet (request or status reply).

    Raises:
        ValueError: An id or code outside one byte, or too many parameter bytes.
    """
    if not 0 <= servo_id <= 0xFE:
        raise ValueError(f"servo id {servo_id} is outside 0..254")
    if not 0 <= code <= 0xFF:
        raise ValueError(f"code {code} is outside one byte")
    if len(params) > MAX_PACKET_PARAMS:
        raise ValueError(f"{len(params)} parameter bytes exceed the {MAX_PACKET_PARAMS}-byte packet limit")
    body = bytes((servo_id, len(params) + 2, code)) + bytes(params)
    return HEADER + body + bytes((checksum(body),))


def ping_packet(servo_id: int) -> bytes:
    """PING one servo; it answers with an empty status reply."""
    return encode(servo_id, Instruction.PING)


def read_packet(servo_id: int, address: int, length: int) -> bytes:
    """READ ``length`` bytes from ``address`` of one servo."""
    return encode(servo_id, Instruction.READ, bytes((address, length)))


def write_packet(servo_id: int, address: int, data: bytes) -> bytes:
    """WRITE ``data`` at ``address`` of one servo (``BROADCAST_ID`` for all, no reply then)."""
    return encode(servo_id, Instruction.WRITE, bytes((address,)) + data)


def sync_read_packet(servo_ids: Iterable[int], address: int, length: int) -> bytes:
    """SYNC_READ: each listed servo replies in turn with its own status packet of ``length`` bytes."""
    return encode(BROADCAST_ID, Instruction.SYNC_READ, bytes((address, length, *servo_ids)))


def sync_write_packet(address: int, data: Mapping[int, bytes]) -> bytes:
    """SYNC_WRITE the same-sized ``data[id]`` at ``address`` of every listed servo; nobody replies.

    Raises:
        ValueError: The data blocks differ in size, or none is given.
    """
    sizes = {len(block) for block in data.values()}
    if len(sizes) != 1:
        raise ValueError(f"sync write needs one data size for all servos, got sizes {sorted(sizes)}")
    params = bytearray((address, sizes.pop()))
    for servo_id, block in data.items():
        params.append(servo_id)
        params += block
    return encode(BROADCAST_ID, Instruction.SYNC_WRITE, params)


def status_packet(servo_id: int, error: int = 0, params: bytes = b"") -> bytes:
    """A servo's status reply (used by the emulator and tests)."""
    return encode(servo_id, error, params)


def decode(buffer: bytes | bytearray) -> tuple[Packet | None, int]:
    """Find the first whole packet in ``buffer``.

    Returns:
        ``(packet, consumed)``: the packet and the bytes it and any junk before it used, or
        ``(None, skip)`` when no whole packet is there yet (``skip`` junk bytes may be dropped).

    Raises:
        ChecksumError: The first framed packet has a wrong checksum (``consumed`` says how long it was).
        PacketError: The first framed packet has an impossible length byte.
    """
    start = buffer.find(HEADER)
    if start < 0:
        # Keep a trailing 0xFF: it may be the first half of the next header.
        return None, len(buffer) - (1 if buffer[-1:] == b"\xff" else 0)
    # Skip a run of 0xFF (a header may be preceded by a stray 0xFF).
    while start + 2 < len(buffer) and buffer[start + 2] == 0xFF:
        start += 1
    if len(buffer) < start + 4:
        return None, start
    length = buffer[start + 3]
    if length < 2:
        raise PacketError(f"packet length byte {length} is below the minimum of 2", start + 4)
    end = start + 4 + length
    if len(buffer) < end:
        return None, start
    body = bytes(buffer[start + 2 : end - 1])
    if checksum(body) != buffer[end - 1]:
        raise ChecksumError(
            f"checksum mismatch for packet from id {body[0]}: got 0x{buffer[end - 1]:02x}, "
            f"expected 0x{checksum(body):02x}",
            end,
        )
    return Packet(servo_id=body[0], code=body[2], params=body[3:]), end


def u16(value: int) -> bytes:
    """Two little-endian bytes of an unsigned 16-bit value."""
    return bytes((value & 0xFF, (value >> 8) & 0xFF))


def from_u16(data: bytes | bytearray, offset: int = 0) -> int:
    """Unsigned 16-bit little-endian value at ``offset``."""
    return data[offset] | (data[offset + 1] << 8)


def encode_sign_magnitude(value: int, sign_bit: int = 15) -> int:
    """Sign-magnitude encoding with the sign in ``sign_bit`` (STS present position and speed).

    Raises:
        ValueError: The magnitude does not fit below the sign bit.
    """
    magnitude = abs(int(value))
    if magnitude >= 1 << sign_bit:
        raise ValueError(f"magnitude {magnitude} does not fit in {sign_bit} bits")
    return magnitude | ((1 << sign_bit) if value < 0 else 0)


def decode_sign_magnitude(raw: int, sign_bit: int = 15) -> int:
    """Inverse of :func:`encode_sign_magnitude`."""
    magnitude = raw & ((1 << sign_bit) - 1)
    return -magnitude if raw >> sign_bit & 1 else magnitude
