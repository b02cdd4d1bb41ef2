"""Run statistics: the achieved rate counts intervals, the live status reads the recent ticks."""

from __future__ import annotations

import subprocess
import sys

import pytest

from openral_core import TickResult
from openral_runner.stats import RunStats


def test_effective_rate_counts_intervals_between_tick_starts() -> None:
    stats = RunStats()
    assert stats.effective_rate(1) == 0.0
    stats.first_start_s, stats.last_start_s = 10.0, 12.0
    assert stats.effective_rate(61) == pytest.approx(30.0)  # 60 intervals in 2 s, not 61 ticks
    stats.reset()
    assert stats.effective_rate(61) == 0.0


def test_live_status_rates_and_percentiles_come_from_the_recent_ticks() -> None:
    stats = RunStats()
    recent = [
        TickResult(
            tick_idx=i, start_ns=i * 10_000_000, tick_ms=1.0 + (i % 2), stale_sensors=["wrist"] if i == 99 else []
        )
        for i in range(100)
    ]
    for tick in recent:
        stats.tick_ms.add(tick.tick_ms)
    stats.missed_slots = 3
    status = stats.live_status(recent, elapsed_s=2.0, rate_hz=100.0)
    assert status["ticks"] == 100.0
    assert status["rate_hz"] == pytest.approx(50.0)  # 100 ticks over 2 s since the start
    assert status["recent_rate_hz"] == pytest.approx(100.0)  # starts 10 ms apart
    assert status["tick_ms_p50"] == pytest.approx(1.5)
    assert status["tick_ms_p99"] == pytest.approx(2.0)
    assert status["missed_slots"] == 3.0
    assert status["stale_sensors"] == 1.0
    empty = RunStats().live_status([], elapsed_s=0.0, rate_hz=30.0)
    assert (empty["rate_hz"], empty["tick_ms_p50"], empty["stale_sensors"]) == (0.0, 0.0, 0.0)


def test_reading_the_status_of_a_run_imports_nothing() -> None:
    """An import on a status thread holds the GIL for tens of ms, stalling the tick that wakes meanwhile."""
    code = (
        "import sys\n"
        "from openral_core import TickResult\n"
        "from openral_runner.stats import RunStats\n"
        "stats = RunStats()\n"
        "recent = [TickResult(tick_idx=i, start_ns=i, tick_ms=1.0) for i in range(10)]\n"
        "before = set(sys.modules)\n"
        "stats.live_status(recent, elapsed_s=1.0, rate_hz=30.0)\n"
        "stats.result(runner_name='r', skill_id=None, rate_hz=30.0, n_ticks=10, stop_reason='max_ticks', metadata={})\n"
        "print(sorted(set(sys.modules) - before))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert proc.stdout.strip() == "[]", proc.stdout
