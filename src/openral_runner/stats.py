"""Bounded per-tick sample storage for honest run statistics at any rate and duration."""

from __future__ import annotations

from typing import Any, Final

import numpy as np

from openral_core import RunResult, StopReason, TickResult, WithheldReason

FAULT_REASONS: Final = frozenset(reason for reason in WithheldReason if reason.is_fault)
"""Withheld reasons that count towards ``max_consecutive_failures``."""

DEFAULT_CAPACITY = 262_144
"""Samples kept for percentiles (~2.4 h at 30 Hz, ~4 min at 1 kHz); mean and max cover every sample."""


class RollingSamples:
    """Preallocated ring of float samples with exact count, mean and max over all samples.

    Percentiles are computed over the most recent ``capacity`` samples. Appending is O(1)
    and allocates nothing, so it is safe on the tick path.
    """

    __slots__ = ("_buffer", "_capacity", "_count", "_max", "_sum")

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        self._capacity = capacity
        self._buffer = np.empty(capacity, dtype=np.float64)
        self.clear()

    def clear(self) -> None:
        """Forget every sample."""
        self._count = 0
        self._sum = 0.0
        self._max = 0.0

    def add(self, value: float) -> None:
        """Record one sample."""
        self._buffer[self._count % self._capacity] = value
        self._count += 1
        self._sum += value
        if value > self._max or self._count == 1:
            self._max = value

    def __len__(self) -> int:
        return self._count

    @property
    def mean(self) -> float:
        """Mean over every sample (0 when empty)."""
        return self._sum / self._count if self._count else 0.0

    @property
    def max(self) -> float:
        """Largest sample (0 when empty)."""
        return self._max

    def window(self) -> np.ndarray:
        """The retained samples (a copy, oldest order not guaranteed)."""
        return self._buffer[: min(self._count, self._capacity)].copy()

    def percentile(self, q: float) -> float:
        """Linear-interpolation percentile ``q`` in [0, 100] over retained samples (0 when empty)."""
        if self._count == 0:
            return 0.0
        return float(np.percentile(self._buffer[: min(self._count, self._capacity)], q))


class RunStats:
    """The counters and samples of one ``run()``: what its :class:`~openral_core.RunResult` reports.

    Plain attributes, updated by the runner on the tick thread and read (without locking) by a
    status display: each is a single number or a :class:`RollingSamples`.
    """

    def __init__(self) -> None:
        # numpy imports ``numpy.ma`` on the first percentile call: ~30-60 ms holding the GIL.
        # Pay it here, before any tick, not when a status thread first reads a running loop.
        np.percentile(np.zeros(2), (50, 99))
        self.tick_ms = RollingSamples()
        self.inference_ms = RollingSamples()
        self.jitter_us = RollingSamples()
        self.overhead_us = RollingSamples()
        self.reset()

    def reset(self) -> None:
        """Zero everything for a new run."""
        self.missed_slots = 0
        self.deadline_misses = 0
        self.budget_violations = 0
        self.dropped = 0
        self.withheld = 0
        self.failed = 0
        self.consecutive_failures = 0
        self.stale_reads = 0
        self.safety_violations = 0
        self.trace_id: str | None = None
        self.run_t0 = 0.0
        self.run_t_end = 0.0
        self.first_start_s = 0.0
        self.last_start_s = 0.0
        for samples in (self.tick_ms, self.inference_ms, self.jitter_us, self.overhead_us):
            samples.clear()

    def count(self, result: TickResult, *, over_budget: bool) -> None:
        """Add one tick: its timings, why its action was withheld, its stale reads and safety violations.

        A withheld fault adds to ``consecutive_failures``; any other tick ends the streak.
        """
        phases_ms = result.sensors_ms + result.world_state_ms + result.inference_ms + result.safety_ms + result.hal_ms
        self.tick_ms.add(result.tick_ms)
        self.inference_ms.add(result.inference_ms)
        self.overhead_us.add(max(0.0, result.tick_ms - phases_ms) * 1e3)
        reason = result.withheld_reason
        if reason is not None:
            self.withheld += 1
            if reason == WithheldReason.DEADLINE:
                self.dropped += 1
        if reason in FAULT_REASONS:
            self.failed += 1
            self.consecutive_failures += 1
        else:
            self.consecutive_failures = 0
        self.stale_reads += len(result.stale_sensors)
        self.safety_violations += len(result.safety_violations)
        if over_budget:
            self.budget_violations += 1

    def effective_rate(self, n_ticks: int) -> float:
        """Achieved rate: intervals between the first and the last tick start, per second."""
        span_s = self.last_start_s - self.first_start_s
        if n_ticks < 2 or span_s <= 0:
            return 0.0
        return (n_ticks - 1) / span_s

    def result(
        self,
        *,
        runner_name: str,
        skill_id: str | None,
        rate_hz: float,
        n_ticks: int,
        stop_reason: StopReason,
        metadata: dict[str, Any],
    ) -> RunResult:
        """The run's result so far."""
        return RunResult(
            runner_name=runner_name,
            skill_id=skill_id,
            rate_hz=rate_hz,
            n_ticks=n_ticks,
            duration_s=max(0.0, self.run_t_end - self.run_t0),
            effective_rate_hz=self.effective_rate(n_ticks),
            tick_ms_mean=self.tick_ms.mean,
            tick_ms_p50=self.tick_ms.percentile(50),
            tick_ms_p99=self.tick_ms.percentile(99),
            tick_ms_max=self.tick_ms.max,
            inference_ms_mean=self.inference_ms.mean,
            inference_ms_p50=self.inference_ms.percentile(50),
            inference_ms_p99=self.inference_ms.percentile(99),
            inference_ms_max=self.inference_ms.max,
            start_jitter_us_p50=self.jitter_us.percentile(50),
            start_jitter_us_p99=self.jitter_us.percentile(99),
            start_jitter_us_max=self.jitter_us.max,
            overhead_us_mean=self.overhead_us.mean,
            missed_slots=self.missed_slots,
            deadline_misses=self.deadline_misses,
            budget_violations=self.budget_violations,
            dropped_actions=self.dropped,
            withheld_actions=self.withheld,
            stale_reads=self.stale_reads,
            safety_violations=self.safety_violations,
            failed_ticks=self.failed,
            stop_reason=stop_reason,
            trace_id=self.trace_id,
            metadata=metadata,
        )

    def live_status(self, recent: list[TickResult], *, elapsed_s: float, rate_hz: float) -> dict[str, float]:
        """A cheap snapshot for a status display.

        ``rate_hz`` is the average since the run started (``elapsed_s`` ago), ``recent_rate_hz``
        over about the last two seconds of ``recent`` ticks; tick percentiles cover ``recent``;
        ``stale_sensors`` counts the sensors stale in the latest tick, ``stale_reads`` every stale
        read so far.
        """
        n = len(self.tick_ms)
        tick_ms = np.fromiter((t.tick_ms for t in recent), dtype=np.float64, count=len(recent))
        recent_rate = 0.0
        window = recent[-(int(2.0 * rate_hz) + 1) :]
        if len(window) >= 2 and window[-1].start_ns > window[0].start_ns:
            recent_rate = (len(window) - 1) / ((window[-1].start_ns - window[0].start_ns) / 1e9)
        p50, p99 = np.percentile(tick_ms, (50, 99)) if recent else (0.0, 0.0)
        return {
            "ticks": float(n),
            "target_hz": rate_hz,
            "rate_hz": n / elapsed_s if elapsed_s > 0 else 0.0,
            "recent_rate_hz": recent_rate,
            "tick_ms_p50": float(p50),
            "tick_ms_p99": float(p99),
            "deadline_misses": float(self.deadline_misses),
            "missed_slots": float(self.missed_slots),
            "dropped_actions": float(self.dropped),
            "withheld_actions": float(self.withheld),
            "stale_sensors": float(len(recent[-1].stale_sensors)) if recent else 0.0,
            "stale_reads": float(self.stale_reads),
            "safety_violations": float(self.safety_violations),
        }
