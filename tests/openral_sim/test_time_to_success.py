"""Time to success over all episodes: failures censored at the limit, quantiles that admit 'beyond the limit'."""

from __future__ import annotations

import pytest

from openral_core import EpisodeResult
from openral_sim.evaluation import summarize
from openral_sim.time_to_success import quantile, solved_by, time_to_success

SIX_OF_TEN = [10, None, 20, 30, None, 40, 50, None, 60, None]
"""Ten episodes: six solved at steps 10..60, four failed (censored at the limit)."""


def test_the_curve_is_the_share_of_all_episodes_solved_by_each_step() -> None:
    assert solved_by(SIX_OF_TEN) == [[10, 0.1], [20, 0.2], [30, 0.3], [40, 0.4], [50, 0.5], [60, 0.6]]
    assert solved_by([5, 5, None, 7]) == [[5, 0.5], [7, 0.75]]


def test_a_quantile_counts_failures_and_is_none_beyond_the_limit() -> None:
    assert quantile(SIX_OF_TEN, 0.5) == 50  # half of all ten, not the median of the six solved (35)
    assert quantile(SIX_OF_TEN, 0.9) is None  # 90 % were never solved within the limit
    assert quantile([8, 9, 10, 11], 0.5) == 9
    assert quantile([], 0.5) is None


def test_the_summary_gives_intervals_that_are_seeded_and_bracket_the_estimate() -> None:
    summary = time_to_success(SIX_OF_TEN)
    assert summary == time_to_success(SIX_OF_TEN)
    assert summary["p50"] == 50
    low, high = summary["p50_ci95"]
    assert low is not None
    assert low <= 50
    assert high is None, "in many resamples fewer than half succeed: the upper end is beyond the limit"
    assert summary["p90"] is None
    assert summary["p90_ci95"][1] is None, "90 % solved is beyond the limit in most resamples"


def test_a_policy_that_always_succeeds_has_finite_intervals() -> None:
    steps = [20 + (k % 7) for k in range(50)]
    summary = time_to_success(steps)
    assert summary["p90"] == pytest.approx(26)
    low, high = summary["p90_ci95"]
    assert low is not None
    assert high is not None
    assert low <= 26 <= high


def test_seconds_are_the_steps_at_the_envs_rate_and_stay_beyond_the_limit_where_they_are() -> None:
    summary = time_to_success(SIX_OF_TEN, control_hz=20.0)
    assert summary["control_hz"] == 20.0
    assert summary["p50_s"] == pytest.approx(50 / 20)
    steps_low, steps_high = summary["p50_ci95"]
    assert steps_high is None
    assert summary["p50_s_ci95"] == [pytest.approx(steps_low / 20), None]
    assert summary["p90_s"] is None
    assert "p50_s" not in time_to_success(SIX_OF_TEN), "no rate, no seconds"


def test_a_rows_seconds_come_from_its_episodes_rate_and_an_older_report_has_none() -> None:
    def episodes(rate: float | None) -> list[EpisodeResult]:
        return [
            EpisodeResult(episode_idx=k, seed=k, success=s is not None, steps=60, steps_to_success=s, control_hz=rate)
            for k, s in enumerate(SIX_OF_TEN)
        ]

    assert summarize(episodes(50.0))["time_to_success"]["p50_s"] == pytest.approx(1.0)
    assert "p50_s" not in summarize(episodes(None))["time_to_success"]
    assert EpisodeResult.model_validate({"episode_idx": 0, "seed": 0, "success": False, "steps": 3}).control_hz is None
