"""What one real-time episode (``virtual_latency: measured``) did with the wall clock: fresh, held and stale steps.

Under real time the wall clock paces the steps and the world does not wait for a late controller:
a tick that overruns its slot is followed by one hold-action step per skipped slot
(:meth:`~openral_sim.runner.SimRunner._on_missed_slots`). :class:`RealTimeTally` classifies every
env step of an episode as the :class:`~openral_core.RealTimeStats` docstring defines, from the
tick's result and the chunk executor's counters around the tick (no hook inside the executor's
tick path), and reports the episode's ratio of stale or held steps and its effective rates.
"""

from __future__ import annotations

from openral_core import RealTimeStats, TickResult
from openral_rskill.executor import ChunkedExecutor


class RealTimeTally:
    """The counts of one episode's env steps under real time, and when its first and last step started.

    Args:
        period_s: The slot each step owns (one period of the paced loop).
    """

    __slots__ = (
        "_no_row_before",
        "_stale_before",
        "first_start_s",
        "fresh_ticks",
        "held_slots",
        "held_ticks",
        "last_start_s",
        "period_s",
        "policy_ticks",
        "stale_ticks",
    )

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.policy_ticks = 0
        self.held_slots = 0
        self.fresh_ticks = 0
        self.held_ticks = 0
        self.stale_ticks = 0
        self.first_start_s: float | None = None
        self.last_start_s = 0.0
        self._no_row_before = 0
        self._stale_before = 0

    def before_tick(self, executor: ChunkedExecutor | None) -> None:
        """Note the executor's counters before a tick, to tell afterwards what the tick sent."""
        if executor is not None:
            self._no_row_before = _no_row(executor)
            self._stale_before = executor.stats.stale_rows

    def after_tick(self, result: TickResult, executor: ChunkedExecutor | None, *, start_s: float) -> None:
        """Classify a policy tick (a step tick of the episode, started at ``start_s``) as fresh, held or stale."""
        self.policy_ticks += 1
        self._stepped_at(start_s)
        no_row = executor is not None and _no_row(executor) > self._no_row_before
        if no_row or not result.action_applied:
            self.held_ticks += 1
            return
        if executor is not None and executor.stats.stale_rows > self._stale_before:
            self.stale_ticks += 1
        else:
            self.fresh_ticks += 1

    def held_slot(self, start_s: float) -> None:
        """Count a skipped slot stepped with the hold action at ``start_s``."""
        self.held_slots += 1
        self._stepped_at(start_s)

    def stats(self) -> RealTimeStats:
        """The episode's counts, ratio and rates."""
        # Each step owns a slot: the episode spans its first step's start to the end of its last step's slot.
        wall_s = 0.0 if self.first_start_s is None else self.last_start_s - self.first_start_s + self.period_s
        return RealTimeStats.of(
            policy_ticks=self.policy_ticks,
            held_slots=self.held_slots,
            fresh_ticks=self.fresh_ticks,
            held_ticks=self.held_ticks,
            stale_ticks=self.stale_ticks,
            wall_s=wall_s,
        )

    def _stepped_at(self, start_s: float) -> None:
        if self.first_start_s is None:
            self.first_start_s = start_s
        self.last_start_s = start_s


def _no_row(executor: ChunkedExecutor) -> int:
    """Ticks on which the executor had no row to send (starved, or its source down)."""
    return executor.stats.starved_ticks + executor.stats.unavailable_ticks
