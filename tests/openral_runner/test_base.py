"""Cadence and deadline semantics of InferenceRunnerBase, on a fake clock (no real sleeping)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from openral_core import (
    DeadlineOverrunPolicy,
    ROSConfigError,
    ROSDeadlineMissed,
    ROSRuntimeError,
    StopReason,
    WithheldReason,
)
from openral_runner.base import InferenceRunnerBase
from openral_runner.testing import FakeClock
from openral_runner.tick_context import TickContext

RATE = 50.0
PERIOD = 1.0 / RATE


class TimedRunner(InferenceRunnerBase):
    """A runner whose ticks take scripted fake time and 'send' when the deadline policy allows."""

    def __init__(self, clock: FakeClock, durations: dict[int, float] | None = None, **kwargs: object) -> None:
        super().__init__(rate_hz=RATE, clock=clock, **kwargs)  # type: ignore[arg-type]
        self.clock = clock
        self.durations = durations or {}
        self.default_duration = 0.2 * PERIOD
        self.starts: list[float] = []
        self.sent: list[int] = []
        self.withhold: dict[int, WithheldReason] = {}

    def _tick_impl(self, tick: TickContext) -> None:
        tick_idx = tick.tick_idx
        self.starts.append(self.clock.now())
        self.clock.advance(self.durations.get(tick_idx, self.default_duration))
        reason = self.withhold.get(tick_idx)
        if reason is None:
            if self._deadline_allows_send():
                self.sent.append(tick_idx)
            else:
                reason = WithheldReason.DEADLINE
        tick.inference_ms = 1.0
        tick.action_applied = reason is None
        tick.withheld = reason


_made: list[TimedRunner] = []


@pytest.fixture(autouse=True)
def _deactivate_runners() -> Iterator[None]:
    """Deactivate every runner a test made: its telemetry worker flushes here, not into a later test."""
    yield
    while _made:
        _made.pop().deactivate()


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock(start_s=1000.0)


def make(clock: FakeClock, durations: dict[int, float] | None = None, **kwargs: object) -> TimedRunner:
    runner = TimedRunner(clock, durations, **kwargs)
    runner.activate()
    _made.append(runner)
    return runner


def test_ticks_start_on_an_absolute_schedule_without_drift(clock: FakeClock) -> None:
    # Varying tick durations below one period must not shift later slots.
    durations = {i: (0.1 + 0.08 * (i % 10)) * PERIOD for i in range(200)}
    runner = make(clock, durations)
    t0 = clock.now()
    result = runner.run(200)
    assert result.n_ticks == 200
    expected = [t0 + k * PERIOD for k in range(200)]
    assert runner.starts == pytest.approx(expected, abs=1e-9)
    assert result.missed_slots == 0
    assert result.effective_rate_hz == pytest.approx(RATE, rel=1e-9)


def test_overrun_skips_to_next_future_slot_without_burst(clock: FakeClock) -> None:
    runner = make(clock, {3: 2.5 * PERIOD})
    t0 = clock.now()
    result = runner.run(8)
    slots = [round((s - t0) / PERIOD, 6) for s in runner.starts]
    # tick 3 starts at slot 3, ends at 5.5 periods: slots 4 and 5 are skipped, phase kept.
    assert slots == [0, 1, 2, 3, 6, 7, 8, 9]
    assert result.missed_slots == 2
    # No two ticks start closer than one period (no catch-up burst).
    gaps = [b - a for a, b in zip(runner.starts, runner.starts[1:], strict=False)]
    assert min(gaps) >= PERIOD - 1e-9


def test_overrun_ending_exactly_on_a_boundary_starts_there(clock: FakeClock) -> None:
    runner = make(clock, {0: 2.0 * PERIOD})
    t0 = clock.now()
    result = runner.run(3)
    slots = [round((s - t0) / PERIOD, 6) for s in runner.starts]
    assert slots == [0, 2, 3]
    assert result.missed_slots == 1


def test_warn_policy_sends_late_action_and_counts_it(clock: FakeClock) -> None:
    runner = make(clock, {2: 1.5 * PERIOD}, deadline_overrun_policy=DeadlineOverrunPolicy.WARN)
    result = runner.run(5)
    assert 2 in runner.sent
    assert result.deadline_misses == 1
    assert result.dropped_actions == 0
    late = runner.recent_ticks[2]
    assert late.deadline_missed
    assert late.lateness_ms == pytest.approx(0.5 * PERIOD * 1e3)


def test_drop_policy_withholds_the_late_action(clock: FakeClock) -> None:
    runner = make(clock, {2: 1.5 * PERIOD}, deadline_overrun_policy=DeadlineOverrunPolicy.DROP)
    result = runner.run(5)
    assert 2 not in runner.sent
    assert runner.sent == [0, 1, 3, 4]
    assert result.deadline_misses == 1
    assert result.dropped_actions == 1
    assert runner.recent_ticks[2].withheld_reason == "deadline"
    assert result.n_ticks == 5


def test_raise_policy_withholds_stops_and_carries_partial_result(clock: FakeClock) -> None:
    runner = make(clock, {3: 1.2 * PERIOD}, deadline_overrun_policy=DeadlineOverrunPolicy.RAISE)
    with pytest.raises(ROSDeadlineMissed) as info:
        runner.run(10)
    assert runner.sent == [0, 1, 2]  # the late action never went out; robot left holding tick 2's
    assert len(runner.starts) == 4  # the loop stopped right after the late tick
    partial = info.value.run_result
    assert partial is not None
    assert partial.n_ticks == 4
    assert partial.deadline_misses == 1
    assert partial.stop_reason == "deadline"
    assert info.value.tick_result is not None
    assert info.value.tick_result.tick_idx == 3


def test_on_time_ticks_are_not_late(clock: FakeClock) -> None:
    runner = make(clock, dict.fromkeys(range(5), 0.99 * PERIOD), deadline_overrun_policy=DeadlineOverrunPolicy.RAISE)
    result = runner.run(5)
    assert result.deadline_misses == 0
    assert runner.sent == [0, 1, 2, 3, 4]


def test_latency_budget_violations_are_counted(clock: FakeClock) -> None:
    durations = {1: 0.6 * PERIOD, 4: 0.7 * PERIOD}
    runner = make(clock, durations, latency_budget_ms=0.5 * PERIOD * 1e3)
    result = runner.run(6)
    assert result.budget_violations == 2
    assert result.deadline_misses == 0


def test_rerun_after_activate_resets_counters_and_tick_index(clock: FakeClock) -> None:
    runner = make(clock, {1: 1.5 * PERIOD})
    first = runner.run(4)
    assert first.deadline_misses == 1
    runner.deactivate()
    runner.durations = {}
    runner.activate()
    runner.starts.clear()
    second = runner.run(3)
    assert second.n_ticks == 3
    assert second.deadline_misses == 0
    assert second.missed_slots == 0
    assert [t.tick_idx for t in runner.recent_ticks] == [0, 1, 2]


def test_run_requires_activate(clock: FakeClock) -> None:
    runner = TimedRunner(clock)
    with pytest.raises(ROSRuntimeError, match="activate"):
        runner.run(1)


def test_consecutive_faults_stop_the_run(clock: FakeClock) -> None:
    runner = make(clock, max_consecutive_failures=3)
    runner.withhold = {2: "skill_error", 4: "read_state", 5: "stale_sensor", 6: "skill_error", 7: "skill_error"}
    result = runner.run(20)
    # 2 alone is reset by tick 3; 4, 5, 6 make three in a row.
    assert result.stop_reason == "faults"
    assert result.n_ticks == 7
    assert result.failed_ticks == 4
    assert result.withheld_actions == 4


def test_safety_withholds_do_not_count_as_faults(clock: FakeClock) -> None:
    runner = make(clock, max_consecutive_failures=2)
    runner.withhold = dict.fromkeys(range(6), "safety")
    result = runner.run(6)
    assert result.stop_reason == "max_ticks"
    assert result.withheld_actions == 6
    assert result.failed_ticks == 0


def test_duration_limit_and_stop_request(clock: FakeClock) -> None:
    runner = make(clock)
    result = runner.run(duration_s=10 * PERIOD)
    assert result.stop_reason == "duration"
    assert result.n_ticks == 10

    runner.activate()
    runner.durations = {}
    calls = 0

    def stop_after_three() -> bool:
        nonlocal calls
        calls += 1
        if calls == 3:
            runner.request_stop()
        return False

    runner._should_terminate = stop_after_three  # type: ignore[method-assign]
    result = runner.run(100)
    assert result.stop_reason == "stop_requested"
    assert result.n_ticks == 3


def test_should_terminate_hook_ends_run(clock: FakeClock) -> None:
    runner = make(clock)
    runner._should_terminate = lambda: len(runner.starts) >= 4  # type: ignore[method-assign]
    result = runner.run(100)
    assert result.stop_reason == "terminated"
    assert result.n_ticks == 4


def test_jitter_and_overhead_statistics(clock: FakeClock) -> None:
    class LateWake(FakeClock):
        def sleep_until(self, deadline_s: float) -> None:
            super().sleep_until(deadline_s)
            self.t += 50e-6  # every wake-up is 50 µs late

    late_clock = LateWake()
    runner = TimedRunner(late_clock)
    runner.activate()
    result = runner.run(20)
    assert result.start_jitter_us_p50 == pytest.approx(50.0, abs=1e-3)
    assert result.start_jitter_us_max == pytest.approx(50.0, abs=1e-3)
    # Each tick is 0.2 periods long with 1 ms reported as inference: the rest is overhead.
    assert result.overhead_us_mean == pytest.approx((0.2 * PERIOD - 1e-3) * 1e6, rel=1e-6)
    assert result.tick_ms_p50 == pytest.approx(0.2 * PERIOD * 1e3)


def test_invalid_rate_is_a_config_error(clock: FakeClock) -> None:
    with pytest.raises(ROSConfigError, match="rate_hz"):
        TimedRunner.__mro__[1].__init__(TimedRunner.__new__(TimedRunner), rate_hz=0.0)  # type: ignore[misc]


def test_standalone_tick_applies_policy(clock: FakeClock) -> None:
    runner = make(clock, {0: 2 * PERIOD}, deadline_overrun_policy=DeadlineOverrunPolicy.RAISE)
    with pytest.raises(ROSDeadlineMissed) as info:
        runner.tick()
    assert info.value.run_result is None
    assert runner.sent == []


def test_a_plain_stop_ends_one_run_and_a_signal_stop_stays_until_deactivate() -> None:
    runner = TimedRunner(FakeClock())
    _made.append(runner)
    runner.activate()
    runner.request_stop()
    assert runner.run(5).n_ticks == 0
    assert runner.run(5).n_ticks == 5  # the next episode ticks again
    runner.request_stop(StopReason.SIGINT)
    assert runner.run(5).stop_reason == StopReason.SIGINT
    assert runner.run(5).n_ticks == 0
    runner.deactivate()
    runner.activate()
    assert runner.run(2).n_ticks == 2
    runner.deactivate()
