"""FeetechBus against the emulator on a real pseudo-terminal: transactions, retries, faults."""

from __future__ import annotations

import time

import pytest

pytest.importorskip("serial", reason="needs the 'serial' extra")

from openral_core import ROSHardwareError
from openral_hal.feetech import protocol as p
from openral_hal.feetech.bus import FeetechBus, ServoNoReply
from openral_hal.feetech.emulator import ServoBusEmulator

IDS = [1, 2, 3]


def test_ping_read_write(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    bus.ping(2)
    assert p.from_u16(bus.read(2, p.Register.MODEL_NUMBER, 2)) == p.STS3215_MODEL_NUMBER
    bus.write(2, p.Register.TORQUE_ENABLE, b"\x01")
    assert emu.torque() == {1: False, 2: True, 3: False}


def test_sync_write_moves_servos_toward_goal_over_the_pty(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    bus.sync_write(p.Register.TORQUE_ENABLE, dict.fromkeys(IDS, b"\x01"))
    bus.sync_write(p.Register.GOAL_POSITION, {1: p.u16(2348), 2: p.u16(1748), 3: p.u16(2048)})
    # The first reading that shows motion (~100 ms before arrival): moving, not teleported.
    deadline = time.monotonic() + 5
    mid = bus.sync_read(IDS, p.Register.PRESENT_POSITION, 4)
    while p.from_u16(mid[1]) == 2048 and time.monotonic() < deadline:
        mid = bus.sync_read(IDS, p.Register.PRESENT_POSITION, 4)
    pos1, speed1 = p.from_u16(mid[1]), p.decode_sign_magnitude(p.from_u16(mid[1], 2))
    assert 2048 < pos1 < 2348  # moving at ~3000 ticks/s, not teleported
    assert speed1 > 0
    assert p.decode_sign_magnitude(p.from_u16(mid[2], 2)) < 0
    done = bus.sync_read(IDS, p.Register.PRESENT_POSITION, 2)
    while p.from_u16(done[1]) != 2348 and time.monotonic() < deadline:
        done = bus.sync_read(IDS, p.Register.PRESENT_POSITION, 2)
    assert {i: p.from_u16(v) for i, v in done.items()} == {1: 2348, 2: 1748, 3: 2048}


def test_torque_off_servo_does_not_move(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    bus.sync_write(p.Register.GOAL_POSITION, {1: p.u16(3000)})
    time.sleep(0.05)
    assert emu.positions()[1] == 2048


def test_timeout_raises_after_configured_retries(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    emu.drop_replies = 10**6
    start = time.monotonic()
    with pytest.raises(ServoNoReply, match=r"failed after 3 attempt\(s\)") as info:
        bus.sync_read(IDS, p.Register.PRESENT_POSITION, 2)
    assert isinstance(info.value, ROSHardwareError)
    assert emu.port in str(info.value)
    assert info.value.missing == IDS
    assert bus.stats.retries == 2
    assert bus.stats.timeouts == 3
    assert emu.requests == 3
    # Each attempt ends at its 100 ms deadline: an attempt without one would wait forever.
    assert time.monotonic() - start < 10 * 3 * bus.timeout_s


def test_one_dropped_reply_is_retried_transparently(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    emu.drop_replies = 1
    assert set(bus.sync_read(IDS, p.Register.PRESENT_POSITION, 2)) == set(IDS)
    assert bus.stats.retries == 1


def test_corrupt_checksum_is_detected_and_retried(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    emu.corrupt_checksum = 1
    replies = bus.sync_read(IDS, p.Register.PRESENT_POSITION, 2)
    assert {i: p.from_u16(v) for i, v in replies.items()} == dict.fromkeys(IDS, 2048)
    assert bus.stats.bad_packets == 1
    assert bus.stats.retries == 1


def test_persistent_corruption_fails_naming_it(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    emu.corrupt_checksum = 10**6
    with pytest.raises(ServoNoReply, match="checksum mismatch"):
        bus.ping(1)


def test_missing_servo_found_by_ping(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    emu.missing_ids = {3}
    assert bus.find(IDS) == [3]


def test_slow_reply_within_timeout_succeeds_beyond_it_fails(emu: ServoBusEmulator) -> None:
    emu.reply_delay_s = 0.01
    with FeetechBus(emu.port, timeout_s=0.05, retries=0) as bus:
        bus.ping(1)
    emu.reply_delay_s = 0.06
    with FeetechBus(emu.port, timeout_s=0.02, retries=0) as bus, pytest.raises(ServoNoReply):
        bus.ping(1)


def test_bus_gone_raises_hardware_error_naming_port(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    emu.disconnect()
    with pytest.raises(ROSHardwareError, match=emu.port):
        bus.sync_read(IDS, p.Register.PRESENT_POSITION, 2)
    with pytest.raises(ROSHardwareError, match="SYNC_WRITE"):
        bus.sync_write(p.Register.GOAL_POSITION, {1: p.u16(100)})


def test_open_missing_port_names_it() -> None:
    with pytest.raises(ROSHardwareError, match="/dev/does-not-exist"):
        FeetechBus("/dev/does-not-exist").open()


def test_not_open_raises() -> None:
    with pytest.raises(ROSHardwareError, match="not open"):
        FeetechBus("/dev/null").ping(1)


def test_a_second_bus_on_the_same_port_is_refused_before_any_byte(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    requests = emu.requests
    second = FeetechBus(emu.port, timeout_s=0.02)
    with pytest.raises(ROSHardwareError, match="is in use by") as info:
        second.open()
    assert emu.port in str(info.value)
    assert "one runner per device" in str(info.value)
    assert not second.is_open
    assert emu.requests == requests, "the refused bus wrote nothing"
    bus.ping(1)  # the owner is unaffected


def test_closing_releases_the_port_for_the_next_owner(emu: ServoBusEmulator) -> None:
    with FeetechBus(emu.port, timeout_s=0.02) as first:
        first.ping(1)
    with FeetechBus(emu.port, timeout_s=0.02) as second:
        second.ping(1)


def test_broadcast_now_goes_out_while_a_transaction_holds_the_bus(bus: FeetechBus, emu: ServoBusEmulator) -> None:
    import threading  # noqa: PLC0415

    bus.sync_write(p.Register.TORQUE_ENABLE, dict.fromkeys(IDS, b"\x01"))
    emu.mute = True  # replies lost: the next read waits out its attempt holding the bus lock
    bus.timeout_s = 4.0  # long enough to be still stuck once the broadcast took effect, however loaded
    bus.retries = 0
    in_transaction = threading.Event()
    emu.on_request = lambda _packet: in_transaction.set()
    failures: list[Exception] = []

    def ping_stuck() -> None:
        try:
            bus.ping(1)
        except ROSHardwareError as exc:
            failures.append(exc)

    stuck = threading.Thread(target=ping_stuck)
    stuck.start()
    assert in_transaction.wait(2)
    emu.on_request = None
    bus.broadcast_now(p.write_packet(p.BROADCAST_ID, p.Register.TORQUE_ENABLE, b"\x00"))
    assert stuck.is_alive(), "the broadcast waited for the stuck transaction"
    deadline = time.monotonic() + 2
    while any(emu.torque().values()) and time.monotonic() < deadline:
        time.sleep(0.005)
    assert not any(emu.torque().values())
    assert stuck.is_alive(), "the torque went off while the transaction still held the bus"
    stuck.join()
    assert len(failures) == 1, "the stuck transaction ran its course and failed"
