"""Paired statistics for two policies run on the same seeds: is B's success rate really different from A's?

Two evaluations on the same seeds are paired: an episode's seed fixes its initial state, so the
episodes that differ are the ones that say something. Two classical tools, both on the 2 × 2
table of paired outcomes:

* the exact McNemar test: under "A and B succeed equally often", each discordant pair (one
  succeeded, the other did not) is a fair coin; the two-sided p is twice the binomial tail of the
  rarer kind, capped at 1;
* Newcombe's interval for the difference of paired proportions (his 1998 method 10): the Wilson
  score intervals of both success rates, combined with the correlation of the paired outcomes.
  It stays inside [-1, 1], behaves at 0 % and 100 %, and is what the report calls the 95 % interval
  of B − A.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from openral_sim.evaluation import WILSON_Z_95, wilson_interval


@dataclass(frozen=True)
class PairedTable:
    """Paired outcomes of A and B: ``both`` succeeded, ``only_a``, ``only_b``, ``neither``."""

    both: int
    only_a: int
    only_b: int
    neither: int

    @classmethod
    def of(cls, a: Sequence[bool], b: Sequence[bool]) -> PairedTable:
        """Count the pairs of two equally long outcome lists (the same seeds, in the same order).

        Raises:
            ValueError: The lists differ in length.
        """
        if len(a) != len(b):
            raise ValueError(f"paired outcomes need equal lengths, got {len(a)} and {len(b)}")
        pairs = list(zip(a, b, strict=True))
        return cls(
            both=sum(x and y for x, y in pairs),
            only_a=sum(x and not y for x, y in pairs),
            only_b=sum(y and not x for x, y in pairs),
            neither=sum(not x and not y for x, y in pairs),
        )

    @property
    def n(self) -> int:
        """Number of pairs."""
        return self.both + self.only_a + self.only_b + self.neither

    @property
    def rate_a(self) -> float:
        """A's success rate."""
        return (self.both + self.only_a) / self.n if self.n else 0.0

    @property
    def rate_b(self) -> float:
        """B's success rate."""
        return (self.both + self.only_b) / self.n if self.n else 0.0


def mcnemar_exact_p(table: PairedTable) -> float:
    """Two-sided exact McNemar p: twice the binomial(discordant, ½) tail of the rarer discordant kind, at most 1."""
    discordant = table.only_a + table.only_b
    if discordant == 0:
        return 1.0
    rarer = min(table.only_a, table.only_b)
    tail = math.ldexp(sum(math.comb(discordant, k) for k in range(rarer + 1)), -discordant)
    return min(1.0, 2.0 * tail)


def newcombe_paired_interval(table: PairedTable, z: float = WILSON_Z_95) -> tuple[float, float]:
    """Newcombe's (1998, method 10) 95 % interval of ``rate_b - rate_a`` for paired outcomes."""
    n = table.n
    if n == 0:
        return (-1.0, 1.0)
    p_a, p_b = table.rate_a, table.rate_b
    low_a, high_a = wilson_interval(table.both + table.only_a, n, z)
    low_b, high_b = wilson_interval(table.both + table.only_b, n, z)
    phi = _phi(table)
    below_b, above_a = p_b - low_b, high_a - p_a
    above_b, below_a = high_b - p_b, p_a - low_a
    difference = p_b - p_a
    lower = difference - math.sqrt(max(0.0, below_b**2 - 2 * phi * below_b * above_a + above_a**2))
    upper = difference + math.sqrt(max(0.0, above_b**2 - 2 * phi * above_b * below_a + below_a**2))
    return (max(-1.0, lower), min(1.0, upper))


def _phi(table: PairedTable) -> float:
    """The correlation of the paired outcomes (0 where a margin is empty)."""
    a, b, c, d = table.both, table.only_a, table.only_b, table.neither
    margins = (a + b) * (c + d) * (a + c) * (b + d)
    return (a * d - b * c) / math.sqrt(margins) if margins else 0.0
