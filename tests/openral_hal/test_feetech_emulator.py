"""The emulated STS3215's register semantics, seen through openral's own FeetechBus on the pty.

Homing offset, position limits, multi-turn mode, Phase bit 4, Lock and power cycles, broadcast
PING, the response level and an ID change, as the STS3215 memory table describes them.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import pytest

pytest.importorskip("serial", reason="needs the 'serial' extra")

import serial

from openral_hal.feetech import protocol as p
from openral_hal.feetech.bus import FeetechBus, ServoNoReply
from openral_hal.feetech.emulator import FACTORY_REGISTERS, ServoBusEmulator
from openral_hal.feetech.protocol import Register

IDS = [1, 2, 3]


def _read(bus: FeetechBus, servo_id: int, register: Register) -> int:
    return p.decode_register(register, bus.read(servo_id, register, p.register_size(register)))


def _write(bus: FeetechBus, servo_id: int, register: Register, value: int) -> None:
    bus.write(servo_id, register, p.encode_register(register, value))


def _settle(bus: FeetechBus, servo_id: int) -> int:
    """The present position once the servo reports it is no longer moving."""
    deadline = time.monotonic() + 5
    while _read(bus, servo_id, Register.MOVING) or _read(bus, servo_id, Register.PRESENT_SPEED):
        assert time.monotonic() < deadline, "the servo never stopped"
    return _read(bus, servo_id, Register.PRESENT_POSITION)


def _wait_for(condition: Callable[[], bool]) -> None:
    deadline = time.monotonic() + 5
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def test_factory_registers_read_back(bus: FeetechBus) -> None:
    assert _read(bus, 2, Register.FIRMWARE_MAJOR_VERSION) == 3
    assert _read(bus, 2, Register.FIRMWARE_MINOR_VERSION) == 10
    assert _read(bus, 2, Register.MODEL_NUMBER) == p.STS3215_MODEL_NUMBER
    assert _read(bus, 2, Register.ID) == 2
    assert _read(bus, 2, Register.MIN_POSITION_LIMIT) == 0
    assert _read(bus, 2, Register.MAX_POSITION_LIMIT) == p.MAX_TICK
    assert _read(bus, 2, Register.HOMING_OFFSET) == 0
    assert _read(bus, 2, Register.PHASE) & 0x10 == 0  # single-turn position feedback
    assert (_read(bus, 2, Register.P_COEFFICIENT), _read(bus, 2, Register.D_COEFFICIENT)) == (32, 32)
    assert _read(bus, 2, Register.I_COEFFICIENT) == 0
    assert _read(bus, 2, Register.MAX_TORQUE_LIMIT) == 1000
    assert _read(bus, 2, Register.TORQUE_LIMIT) == 1000  # SRAM copy of the EEPROM limit at power-on
    assert _read(bus, 2, Register.PROTECTION_CURRENT) == FACTORY_REGISTERS[Register.PROTECTION_CURRENT] > 0
    assert _read(bus, 2, Register.OVERLOAD_TORQUE) == FACTORY_REGISTERS[Register.OVERLOAD_TORQUE] > 0
    assert _read(bus, 2, Register.OPERATING_MODE) == 0
    assert _read(bus, 2, Register.LOCK) == 0
    assert _read(bus, 2, Register.TORQUE_ENABLE) == 0
    assert _read(bus, 2, Register.GOAL_POSITION) == _read(bus, 2, Register.PRESENT_POSITION) == 2048
    assert _read(bus, 2, Register.PRESENT_VOLTAGE) > _read(bus, 2, Register.MIN_VOLTAGE_LIMIT)


def test_homing_offset_shifts_the_present_position_and_the_goal_frame(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    _write(bus, 1, Register.HOMING_OFFSET, -1000)
    assert bus.read(1, Register.HOMING_OFFSET, 2) == bytes((0xE8, 0x0B))  # 1000 | sign bit 11
    assert _read(bus, 1, Register.PRESENT_POSITION) == 3048  # encoder 2048 less -1000
    _write(bus, 1, Register.HOMING_OFFSET, 500)
    assert _read(bus, 1, Register.PRESENT_POSITION) == 1548
    emu.move_by_hand(1, 100)
    assert _read(bus, 1, Register.PRESENT_POSITION) == 3696  # 100 - 500, wrapped into the turn
    emu.move_by_hand(1, 2048)
    _write(bus, 1, Register.TORQUE_ENABLE, 1)
    _write(bus, 1, Register.GOAL_POSITION, 1000)  # a goal in the offset frame
    assert _settle(bus, 1) == 1000
    assert emu.encoders()[1] == 1500
    assert emu.positions()[1] == 1000


def test_position_limits_clamp_the_goal(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    _write(bus, 2, Register.MIN_POSITION_LIMIT, 1500)
    _write(bus, 2, Register.MAX_POSITION_LIMIT, 2500)
    _write(bus, 2, Register.TORQUE_ENABLE, 1)
    _write(bus, 2, Register.GOAL_POSITION, 3000)
    assert _settle(bus, 2) == 2500
    assert _read(bus, 2, Register.GOAL_POSITION) == 3000  # the register keeps what was written
    _write(bus, 2, Register.GOAL_POSITION, 100)
    assert _settle(bus, 2) == 1500


def test_limits_apply_in_the_homing_offset_frame(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    _write(bus, 3, Register.HOMING_OFFSET, 1000)  # present 1048
    _write(bus, 3, Register.MAX_POSITION_LIMIT, 1200)
    _write(bus, 3, Register.TORQUE_ENABLE, 1)
    _write(bus, 3, Register.GOAL_POSITION, 2000)
    assert _settle(bus, 3) == 1200
    assert emu.encoders()[3] == 2200


def test_both_limits_zero_is_multi_turn_and_phase_bit_4_reports_the_full_angle(bus: FeetechBus) -> None:
    _write(bus, 1, Register.MAX_POSITION_LIMIT, 0)
    _write(bus, 1, Register.TORQUE_ENABLE, 1)
    _write(bus, 1, Register.GOAL_POSITION, 5000)  # beyond one turn: no clamp in multi-turn mode
    assert _settle(bus, 1) == 5000 - p.TICKS_PER_REV  # single-turn feedback wraps the reading
    _write(bus, 1, Register.PHASE, _read(bus, 1, Register.PHASE) | 0x10)
    assert _read(bus, 1, Register.PRESENT_POSITION) == 5000
    _write(bus, 1, Register.GOAL_POSITION, -300)  # sign bit 15
    assert _settle(bus, 1) == -300


def test_an_eeprom_write_under_lock_1_is_lost_at_power_off(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    _write(bus, 1, Register.LOCK, 1)
    _write(bus, 1, Register.P_COEFFICIENT, 16)
    assert _read(bus, 1, Register.P_COEFFICIENT) == 16  # in effect at once
    _write(bus, 1, Register.LOCK, 0)
    _write(bus, 1, Register.D_COEFFICIENT, 20)  # saves this byte, not the earlier unsaved one
    _write(bus, 2, Register.P_COEFFICIENT, 20)  # Lock 0: saved
    _write(bus, 2, Register.TORQUE_ENABLE, 1)
    emu.power_cycle()
    assert _read(bus, 1, Register.P_COEFFICIENT) == 32
    assert _read(bus, 1, Register.D_COEFFICIENT) == 20
    assert _read(bus, 2, Register.P_COEFFICIENT) == 20
    assert emu.torque() == dict.fromkeys(IDS, False)
    assert _read(bus, 1, Register.LOCK) == 0


def test_read_only_registers_ignore_writes(bus: FeetechBus) -> None:
    _write(bus, 1, Register.PRESENT_POSITION, 100)
    _write(bus, 1, Register.FIRMWARE_MINOR_VERSION, 9)
    assert _read(bus, 1, Register.PRESENT_POSITION) == 2048
    assert _read(bus, 1, Register.FIRMWARE_MINOR_VERSION) == 10


def test_broadcast_ping_is_answered_by_every_servo_in_id_order() -> None:
    with ServoBusEmulator([3, 1, 2]) as emulator, serial.Serial(emulator.port, timeout=0.05) as port:
        port.write(p.ping_packet(p.BROADCAST_ID))
        buffer = bytearray()
        replies: list[int] = []
        deadline = time.monotonic() + 5
        while len(replies) < 3 and time.monotonic() < deadline:
            buffer += port.read(64)
            packet, used = p.decode(buffer)
            del buffer[:used]
            if packet is not None:
                replies.append(packet.servo_id)
        assert replies == [1, 2, 3]


def test_a_broadcast_write_is_executed_and_answered_by_none(emu: ServoBusEmulator) -> None:
    with serial.Serial(emu.port, timeout=0.05) as port:
        port.write(p.write_packet(p.BROADCAST_ID, Register.TORQUE_ENABLE, b"\x01"))
        _wait_for(lambda: emu.torque() == dict.fromkeys(IDS, True))
        port.write(p.ping_packet(2))  # the next reply on the line is the ping's: nothing came before it
        reply = port.read(6)
    assert p.decode(reply)[0] == p.Packet(servo_id=2, code=0, params=b"")


def test_response_level_0_answers_only_read_and_ping(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    bus.sync_write(Register.RESPONSE_STATUS_LEVEL, {2: b"\x00"})  # a write that needs no reply
    _wait_for(lambda: emu.servos[2].register(Register.RESPONSE_STATUS_LEVEL) == 0)
    with pytest.raises(ServoNoReply):
        _write(bus, 2, Register.TORQUE_ENABLE, 1)
    assert emu.torque()[2]  # executed, just not acknowledged
    bus.ping(2)
    assert _read(bus, 2, Register.RESPONSE_STATUS_LEVEL) == 0


def test_a_written_id_moves_the_servo_to_it(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    _write(bus, 3, Register.ID, 7)  # acknowledged from the old id
    bus.ping(7)
    assert bus.find([3, 7]) == [3]
    assert sorted(emu.servos) == [1, 2, 7]
    _write(bus, 7, Register.ID, 1)  # taken: the emulator keeps one servo per id
    assert sorted(emu.servos) == [1, 2, 7]
    assert _read(bus, 7, Register.ID) == 7
    _write(bus, 2, Register.LOCK, 1)
    _write(bus, 2, Register.ID, 9)  # in effect, but not saved
    bus.ping(9)
    emu.power_cycle()
    assert bus.find([2, 7, 9]) == [9]


def test_servos_configured_earlier_start_with_their_registers() -> None:
    registers = {2: {Register.HOMING_OFFSET: 500, Register.MIN_POSITION_LIMIT: 1000}}
    with (
        ServoBusEmulator(IDS, initial_ticks={2: 3000}, registers=registers) as emulator,
        FeetechBus(emulator.port, timeout_s=0.02) as bus,
    ):
        assert _read(bus, 2, Register.PRESENT_POSITION) == 2500
        assert _read(bus, 2, Register.GOAL_POSITION) == 2500  # torque on would hold the pose
        assert _read(bus, 2, Register.MIN_POSITION_LIMIT) == 1000
        assert _read(bus, 1, Register.HOMING_OFFSET) == 0
        _write(bus, 2, Register.TORQUE_ENABLE, 1)
        assert _settle(bus, 2) == 2500
        emulator.power_cycle()  # the given registers are the servo's EEPROM
        assert _read(bus, 2, Register.HOMING_OFFSET) == 500
