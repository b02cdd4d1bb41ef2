"""What ``RunResult.effective_rate_hz`` and ``duration_s`` mean, pinned on a fake clock."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from openral_core import RunResult
from openral_runner.base import InferenceRunnerBase
from openral_runner.testing import FakeClock
from openral_runner.tick_context import TickContext

RATE = 10_000.0
PERIOD = 1.0 / RATE
TICKS = 1000
STALL_S = 0.00405  # 40.5 periods


class StallingRunner(InferenceRunnerBase):
    """Ticks take a tenth of a period, the last one ``STALL_S``."""

    def __init__(self, clock: FakeClock) -> None:
        super().__init__(rate_hz=RATE, clock=clock)
        self.clock = clock
        self.starts: list[float] = []

    def _tick_impl(self, tick: TickContext) -> None:
        self.starts.append(self.clock.now())
        self.clock.advance(STALL_S if tick.tick_idx == TICKS - 1 else 0.1 * PERIOD)
        tick.action_applied = True


@pytest.fixture
def runner() -> Iterator[StallingRunner]:
    made = StallingRunner(FakeClock(start_s=500.0))
    made.activate()
    yield made
    made.deactivate()


def test_the_rate_spans_tick_starts_and_the_duration_runs_to_the_last_ticks_end(runner: StallingRunner) -> None:
    t0 = runner.clock.now()
    result = runner.run(TICKS)
    assert result.n_ticks == TICKS
    # The ticks kept their schedule: the rate is the one asked for, whatever the last tick took.
    span_s = runner.starts[-1] - runner.starts[0]
    assert result.effective_rate_hz == pytest.approx((TICKS - 1) / span_s, rel=1e-12)
    assert result.effective_rate_hz == pytest.approx(RATE, rel=1e-9)
    # The duration is the run's wall time, to the end of the stalled last tick.
    assert result.duration_s == pytest.approx((TICKS - 1) * PERIOD + STALL_S, rel=1e-9)
    assert result.duration_s == pytest.approx(runner.clock.now() - t0, rel=1e-12)
    # So n_ticks / duration_s reads about 4 % lower; the stall is in tick_ms_max and missed_slots.
    assert 0.95 < TICKS / result.duration_s / RATE < 0.97
    assert result.tick_ms_max == pytest.approx(STALL_S * 1e3, rel=1e-6)
    assert result.missed_slots == 40  # the slots the stall ran over


def test_the_fields_say_so() -> None:
    fields = RunResult.model_fields
    rate = fields["effective_rate_hz"].description or ""
    duration = fields["duration_s"].description or ""
    assert "(n_ticks - 1) / (last tick's start - first tick's start)" in rate
    assert "to the end of its last tick" in duration
    assert "n_ticks / duration_s reads below effective_rate_hz" in duration
