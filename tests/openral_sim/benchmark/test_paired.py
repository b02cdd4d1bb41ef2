"""Paired statistics of two policies on the same seeds, against hand-computed cases and by simulation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from openral_sim.benchmark.paired import PairedTable, mcnemar_exact_p, newcombe_paired_interval
from openral_sim.evaluation import WILSON_Z_95


def test_the_table_counts_pairs_by_seed_order() -> None:
    a = [True, True, False, False, True]
    b = [True, False, True, False, True]
    assert PairedTable.of(a, b) == PairedTable(both=2, only_a=1, only_b=1, neither=1)
    with pytest.raises(ValueError, match="equal lengths"):
        PairedTable.of(a, b[:-1])


@pytest.mark.parametrize(
    ("only_a", "only_b", "p"),
    [
        (1, 9, 22 / 1024),  # 2 × (C(10,0) + C(10,1)) / 2^10
        (9, 1, 22 / 1024),
        (0, 6, 2 / 64),  # 2 × C(6,0) / 2^6
        (3, 3, 1.0),  # 2 × 42/64 = 1.3125, capped
        (0, 0, 1.0),  # no discordant pair: no evidence either way
        (2, 5, 2 * (1 + 7 + 21) / 128),
    ],
)
def test_exact_mcnemar_p_is_twice_the_rarer_binomial_tail(only_a: int, only_b: int, p: float) -> None:
    table = PairedTable(both=17, only_a=only_a, only_b=only_b, neither=11)
    assert mcnemar_exact_p(table) == pytest.approx(p, rel=1e-12)


def test_concordant_pairs_give_an_interval_around_zero_that_narrows_with_more_pairs() -> None:
    small = newcombe_paired_interval(PairedTable(both=6, only_a=0, only_b=0, neither=4))
    large = newcombe_paired_interval(PairedTable(both=600, only_a=0, only_b=0, neither=400))
    assert small[0] < 0 < small[1]
    assert large[0] < 0 < large[1]
    assert large[1] - large[0] < small[1] - small[0]


def test_the_interval_is_the_differences_and_stays_inside_minus_one_to_one() -> None:
    low, high = newcombe_paired_interval(PairedTable(both=0, only_a=0, only_b=10, neither=0))
    assert low > 0.5
    assert high == 1.0
    low, high = newcombe_paired_interval(PairedTable(both=0, only_a=10, only_b=0, neither=0))
    assert low == -1.0
    assert high < -0.5


def test_for_many_pairs_it_agrees_with_the_normal_approximation() -> None:
    table = PairedTable(both=9000, only_a=1500, only_b=2500, neither=7000)
    n = table.n
    difference = (table.only_b - table.only_a) / n
    spread = math.sqrt((table.only_a + table.only_b) / n - difference**2) / math.sqrt(n)
    low, high = newcombe_paired_interval(table)
    assert low == pytest.approx(difference - WILSON_Z_95 * spread, abs=5e-4)
    assert high == pytest.approx(difference + WILSON_Z_95 * spread, abs=5e-4)


def test_it_covers_the_true_difference_about_95_percent_of_the_time() -> None:
    """Pairs drawn from a known joint law (A 60 %, B 70 %, correlated), 50 pairs a study, 2000 studies."""
    rng = np.random.default_rng(7)
    joint = {"both": 0.5, "only_a": 0.1, "only_b": 0.2, "neither": 0.2}
    truth = (joint["both"] + joint["only_b"]) - (joint["both"] + joint["only_a"])
    covered = 0
    studies = 2000
    for counts in rng.multinomial(50, list(joint.values()), size=studies):
        low, high = newcombe_paired_interval(PairedTable(*(int(c) for c in counts)))
        covered += low <= truth <= high
    assert 0.93 <= covered / studies <= 0.975
