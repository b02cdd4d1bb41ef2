"""Feetech packet framing: byte-exact requests, checksum, status decoding, sign-magnitude."""

from __future__ import annotations

import pytest

from openral_hal.feetech import protocol as p


def test_ping_packet_is_byte_exact() -> None:
    # FF FF 01 02 01 ~(01+02+01)=0xFB
    assert p.ping_packet(1) == bytes([0xFF, 0xFF, 0x01, 0x02, 0x01, 0xFB])


def test_sync_read_layout() -> None:
    packet = p.sync_read_packet([1, 2], p.Register.PRESENT_POSITION, 2)
    body = [0xFE, 0x06, 0x82, 56, 2, 1, 2]
    assert packet == bytes([0xFF, 0xFF, *body, ~sum(body) & 0xFF])


def test_sync_write_layout_and_size_check() -> None:
    packet = p.sync_write_packet(p.Register.GOAL_POSITION, {1: p.u16(2048), 2: p.u16(100)})
    body = [0xFE, 2 * 3 + 4, 0x83, 42, 2, 1, 0x00, 0x08, 2, 100, 0]
    assert packet == bytes([0xFF, 0xFF, *body, ~sum(body) & 0xFF])
    with pytest.raises(ValueError, match="one data size"):
        p.sync_write_packet(42, {1: b"\x00", 2: b"\x00\x00"})


def test_write_and_read_packets() -> None:
    assert p.write_packet(3, p.Register.TORQUE_ENABLE, b"\x01")[2:6] == bytes([3, 4, 0x03, 40])
    assert p.read_packet(3, 56, 4)[2:7] == bytes([3, 4, 0x02, 56, 4])


def test_decode_status_with_leading_junk_and_partial() -> None:
    reply = p.status_packet(5, 0, p.u16(1234))
    buffer = bytearray(b"\x00\x13" + reply + reply[:3])
    packet, used = p.decode(buffer)
    assert packet == p.Packet(servo_id=5, code=0, params=p.u16(1234))
    assert used == 2 + len(reply)
    rest, skip = p.decode(buffer[used:])
    assert rest is None
    assert skip == 0


def test_decode_detects_corrupt_checksum() -> None:
    reply = bytearray(p.status_packet(2, 0, b"\x01\x02"))
    reply[-1] ^= 0x01
    with pytest.raises(p.ChecksumError) as info:
        p.decode(reply)
    assert info.value.consumed == len(reply)


def test_error_byte_flags() -> None:
    packet, _ = p.decode(p.status_packet(1, 0x24))
    assert packet is not None
    assert packet.error == p.ServoError.OVERLOAD | p.ServoError.OVERHEAT


@pytest.mark.parametrize(("value", "raw"), [(0, 0), (5, 5), (-5, 0x8005), (32767, 0x7FFF), (-32767, 0xFFFF)])
def test_sign_magnitude_roundtrip(value: int, raw: int) -> None:
    assert p.encode_sign_magnitude(value) == raw
    assert p.decode_sign_magnitude(raw) == value


def test_resolution() -> None:
    assert p.TICKS_PER_REV == 4096
    assert pytest.approx(2 * 3.141592653589793) == p.RAD_PER_TICK * 4096


@pytest.mark.parametrize(
    ("register", "value", "data"),
    [
        (p.Register.HOMING_OFFSET, -1000, bytes((0xE8, 0x0B))),  # sign bit 11
        (p.Register.HOMING_OFFSET, 2047, bytes((0xFF, 0x07))),
        (p.Register.GOAL_POSITION, -300, bytes((0x2C, 0x81))),  # sign bit 15
        (p.Register.MAX_POSITION_LIMIT, 4095, bytes((0xFF, 0x0F))),
        (p.Register.PHASE, 0x1C, bytes((0x1C,))),
    ],
)
def test_register_encoding_roundtrip(register: p.Register, value: int, data: bytes) -> None:
    assert p.encode_register(register, value) == data
    assert p.decode_register(register, data) == value


@pytest.mark.parametrize(("register", "value"), [(p.Register.HOMING_OFFSET, 2048), (p.Register.PHASE, 256)])
def test_a_value_that_does_not_fit_its_register_is_refused(register: p.Register, value: int) -> None:
    with pytest.raises(ValueError, match=register.name):
        p.encode_register(register, value)
