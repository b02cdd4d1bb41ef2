"""The loop's health for the console, read from a running runner (duck-typed: hardware or simulation).

:func:`runner_status` is what a command hands the console as its status source. It reads what
runners expose for status displays: ``live_status()`` (rates, tick percentiles, counters),
``recent_ticks`` (withheld reasons, stale sensors, tick-start jitter), ``executor.stats`` for a
chunking skill, ``skill_id``, ``task`` and ``takeover`` when a runner has one. It runs on the
console's thread, a few times a second; the tick thread only appends to ``recent_ticks``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np

from openral_core import TickResult


def runner_status(runner: Any) -> dict[str, Any]:
    """The health dict the page shows: ``live``, ``withheld``, ``stale_sensors``, ``executor``, ids, takeover."""
    recent: list[TickResult] = list(runner.recent_ticks)  # one copy: the tick thread appends meanwhile
    live: dict[str, Any] = dict(runner.live_status())
    if "start_jitter_us_p99" not in live:
        live["start_jitter_us_p99"] = start_jitter_p99_us(recent, float(live.get("target_hz") or runner.rate_hz))
    if getattr(runner, "free_running", False):
        live["start_jitter_us_p99"] = None  # no schedule, no jitter
    withheld = Counter(str(t.withheld_reason) for t in recent if t.withheld_reason is not None)
    return {
        "skill_id": runner.skill_id,
        "task": getattr(runner, "task", None),
        "live": live,
        "withheld": dict(withheld.most_common()),
        "withheld_window": len(recent),
        "stale_sensors": list(recent[-1].stale_sensors) if recent else [],
        "executor": executor_status(getattr(runner, "executor", None)),
        "takeover": takeover_status(getattr(runner, "takeover", None)),
    }


def start_jitter_p99_us(recent: Sequence[TickResult], rate_hz: float) -> float | None:
    """p99 of how late the recent ticks started against their slots, from their start stamps alone.

    Slots lie on one grid (``t0 + k / rate``), so each start's offset from the grid is its jitter
    plus one constant phase; the smallest offset is taken as the phase. Exact while jitter stays
    under half a period (a later start is a missed slot, which is counted apart).
    """
    if len(recent) < 2 or rate_hz <= 0:
        return None
    period_ns = 1e9 / rate_hz
    starts = np.fromiter((t.start_ns for t in recent), dtype=np.float64, count=len(recent))
    offsets = np.mod(starts - starts[0], period_ns)
    offsets[offsets > period_ns / 2] -= period_ns
    jitter_us = (offsets - offsets.min()) / 1e3
    return float(np.percentile(jitter_us, 99))


def executor_status(executor: Any) -> dict[str, Any] | None:
    """A chunking skill's executor: chunk delay (latest, max of recent), starved ticks, whether the fallback acts."""
    if executor is None:
        return None
    stats = executor.stats
    delays = list(stats.delays_ticks)
    return {
        "chunk_delay_ticks": delays[-1] if delays else None,
        "chunk_delay_ticks_max": max(delays) if delays else None,
        "requests": stats.requests,
        "chunks_used": stats.chunks_used,
        "starved_ticks": stats.starved_ticks,
        "unavailable_ticks": stats.unavailable_ticks,
        "errors": stats.errors,
        "fallback_active": _fallback_active(executor),
    }


def _fallback_active(executor: Any) -> bool | None:
    """Whether the executor has starved past its allowance and hands the ticks to the fallback skill."""
    active = getattr(executor, "fallback_active", None)
    return active if isinstance(active, bool) else None


def takeover_status(takeover: Any) -> dict[str, Any] | None:
    """Who is in control when the runner supports takeover (``None`` when it does not)."""
    if takeover is None:
        return None
    return {
        "human_in_control": bool(getattr(takeover, "human_in_control", False)),
        "skill_id": getattr(takeover, "skill_id", None),
    }
