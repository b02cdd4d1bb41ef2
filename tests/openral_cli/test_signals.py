"""StopSignals: many signals, one orderly stop; copies merged; two more within a second force the escape."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from openral_cli.signals import DUPLICATE_WINDOW_S, FORCE_WINDOW_S, StopSignals
from openral_core import ROSStopRequested


class Recorder:
    def __init__(self) -> None:
        self.said: list[str] = []
        self.stops: list[str] = []
        self.forced: list[str] = []
        self.exits: list[int] = []


def make() -> tuple[StopSignals, Recorder]:
    rec = Recorder()
    signals = StopSignals(say=rec.said.append, exit_process=rec.exits.append)
    signals.on_stop(rec.stops.append)
    signals.on_force(lambda: rec.forced.append("torque off"))
    return signals, rec


def test_first_signal_asks_for_one_stop_and_copies_are_merged() -> None:
    signals, rec = make()
    signals.deliver(signal.SIGTERM, 10.0)
    signals.deliver(signal.SIGTERM, 10.0 + DUPLICATE_WINDOW_S / 2)  # uv's forwarded copy
    assert rec.stops == ["signal:SIGTERM"]
    assert len(rec.said) == 1
    assert signals.exit_code == 143
    with pytest.raises(ROSStopRequested) as info:
        signals.check()
    assert info.value.reason == "signal:SIGTERM"


def test_further_signals_only_remind_unless_two_come_within_the_window() -> None:
    signals, rec = make()
    signals.deliver(signal.SIGINT, 0.0)
    signals.deliver(signal.SIGINT, 1.0)
    signals.deliver(signal.SIGINT, 1.0 + FORCE_WINDOW_S + 0.5)  # too late to pair with the previous one
    assert rec.stops == ["signal:SIGINT"]
    assert rec.forced == []
    assert rec.exits == []
    assert sum("already stopping" in line for line in rec.said) == 2


def test_two_more_within_a_second_force_torque_off_then_exit_with_the_first_signals_code() -> None:
    signals, rec = make()
    signals.deliver(signal.SIGINT, 0.0)
    signals.deliver(signal.SIGTERM, 0.5)
    signals.deliver(signal.SIGTERM, 0.5 + DUPLICATE_WINDOW_S + 0.1)
    assert rec.forced == ["torque off"]
    assert rec.exits == [130]
    assert signals.forced


def test_hammering_faster_than_the_copy_window_still_forces() -> None:
    signals, rec = make()
    for k in range(12):
        signals.deliver(signal.SIGINT, k * 0.15)
    assert rec.exits == [130]


def test_a_stuck_emergency_action_does_not_hold_the_exit(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("openral_cli.signals.FORCE_DEADLINE_S", 0.2)
    rec = Recorder()
    signals = StopSignals(say=rec.said.append, exit_process=rec.exits.append)
    never = threading.Event()
    signals.on_force(never.wait)
    delivering = threading.Thread(target=lambda: [signals.deliver(signal.SIGTERM, t) for t in (0.0, 0.5, 0.9)])
    delivering.start()
    delivering.join(10.0)  # the 0.2 s deadline; the action itself never returns
    stuck = delivering.is_alive()
    never.set()
    delivering.join()
    assert not stuck, "the exit waited for the stuck emergency action"
    assert rec.exits == [143]


def test_late_registration_sees_an_earlier_signal() -> None:
    signals, _rec = make()
    signals.deliver(signal.SIGTERM, 0.0)
    late: list[str] = []
    signals.on_stop(late.append)
    assert late == ["signal:SIGTERM"]


def test_real_signals_reach_the_watcher_and_handlers_are_restored() -> None:
    before = signal.getsignal(signal.SIGTERM)
    stops: list[str] = []
    got = threading.Event()
    with StopSignals(say=lambda _text: None, exit_process=lambda _code: None) as signals:
        signals.on_stop(lambda reason: (stops.append(reason), got.set()))
        os.kill(os.getpid(), signal.SIGTERM)  # handled: the process does not die
        assert got.wait(5)
    assert stops == ["signal:SIGTERM"]
    assert signal.getsignal(signal.SIGTERM) is before


def test_the_watcher_sees_a_signal_while_the_main_thread_is_blocked() -> None:
    """The escape must work when the main thread is stuck in C code and runs no Python handler."""
    got = threading.Event()
    with StopSignals(say=lambda _text: None, exit_process=lambda _code: None) as signals:
        signals.on_stop(lambda _reason: got.set())
        threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()
        read_fd, write_fd = os.pipe()
        try:
            # Blocked in select(2) by a C call that PEP 475 retries: no Python code runs meanwhile,
            # yet the watcher thread gets the signal through the wakeup descriptor.
            threading.Timer(1.0, os.write, (write_fd, b"x")).start()
            os.read(read_fd, 1)
            assert got.is_set()
        finally:
            os.close(read_fd)
            os.close(write_fd)
