"""Shared fixtures of the HAL tests: an emulated three-servo bus and openral's bus client on it."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from openral_hal.feetech.emulator import ServoBusEmulator

SERVO_IDS = [1, 2, 3]


@pytest.fixture
def emu() -> Iterator[ServoBusEmulator]:
    """Three emulated STS3215 servos (ids 1..3) on a pseudo-terminal."""
    with ServoBusEmulator(SERVO_IDS) as emulator:
        yield emulator


@pytest.fixture
def bus(emu: ServoBusEmulator) -> Iterator[object]:
    """openral's Feetech bus client on :func:`emu`'s port (100 ms per attempt, two retries).

    A present servo answers in well under a millisecond; the deadline is for a loaded test machine,
    where the emulator's thread may wait tens of milliseconds for a CPU.
    """
    pytest.importorskip("serial", reason="needs the 'serial' extra")
    from openral_hal.feetech.bus import FeetechBus  # noqa: PLC0415  (pyserial: the 'serial' extra)

    with FeetechBus(emu.port, timeout_s=0.1, retries=2) as client:
        yield client
