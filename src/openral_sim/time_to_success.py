"""Time to success as a distribution over all episodes, failures included as censored.

A mean of the successful episodes' steps hides the failures: a policy that solves 10 % quickly looks
faster than one that solves 90 % a little slower. Here every episode counts. A failure is
*censored* at its step limit (it had not succeeded by then), and since every episode of a row has
the same limit, the survival-style curve, the share of all episodes solved by step ``s``, is the
Kaplan-Meier estimate and needs nothing more than counting. A quantile (p50, p90) is the first
step by which that share of all episodes succeeded; where the share is never reached it is
``None`` (beyond the limit), never a number computed from the successes alone. Intervals are a
seeded bootstrap over episodes, so a report reproduces.

In seconds of simulated time: a step lasts ``1 / control_hz`` (the env's rate, the same for
every episode of a row), so each quantile and interval end in seconds (``p50_s``, ``p50_s_ci95``)
is its step divided by the rate; the curve stays in steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Final

import numpy as np

QUANTILES: Final = (0.5, 0.9)
BOOTSTRAP_RESAMPLES: Final = 2000
BOOTSTRAP_SEED: Final = 0


def solved_by(steps_to_success: Sequence[int | None]) -> list[list[float]]:
    """The curve: ``[step, share of all episodes succeeded by it]`` at each step an episode succeeded."""
    n = len(steps_to_success)
    steps = sorted(s for s in steps_to_success if s is not None)
    curve: list[list[float]] = []
    for i, step in enumerate(steps, start=1):
        if curve and curve[-1][0] == step:
            curve[-1][1] = i / n
        else:
            curve.append([float(step), i / n])
    return curve


def quantile(steps_to_success: Sequence[int | None], q: float) -> float | None:
    """The first step by which a share ``q`` of all episodes had succeeded, or ``None`` (never, in the limit)."""
    n = len(steps_to_success)
    needed = int(np.ceil(q * n - 1e-9))
    steps = sorted(s for s in steps_to_success if s is not None)
    if n == 0 or needed > len(steps):
        return None
    return float(steps[max(needed, 1) - 1])


def time_to_success(steps_to_success: Sequence[int | None], control_hz: float | None = None) -> dict[str, Any]:
    """The curve, and each quantile with its bootstrap 95 % interval (an end ``None``: beyond the limit).

    With the env's ``control_hz``, also each quantile and its interval in simulated seconds.
    """
    summary: dict[str, Any] = {"n_episodes": len(steps_to_success), "solved_by": solved_by(steps_to_success)}
    values = np.array([np.nan if s is None else s for s in steps_to_success], dtype=float)
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    draws = values[rng.integers(0, len(values), size=(BOOTSTRAP_RESAMPLES, len(values)))] if len(values) else None
    for q in QUANTILES:
        key = f"p{round(q * 100)}"
        summary[key] = step = quantile(steps_to_success, q)
        summary[f"{key}_ci95"] = interval = _interval(draws, q)
        if control_hz is not None:
            summary[f"{key}_s"] = _seconds(step, control_hz)
            summary[f"{key}_s_ci95"] = None if interval is None else [_seconds(end, control_hz) for end in interval]
    if control_hz is not None:
        summary["control_hz"] = control_hz
    return summary


def _seconds(step: float | None, control_hz: float) -> float | None:
    return None if step is None else step / control_hz


def _interval(draws: np.ndarray | None, q: float) -> list[float | None] | None:
    """Percentile interval of the quantile over bootstrap resamples; one that never reaches it counts as beyond."""
    if draws is None:
        return None
    n = draws.shape[1]
    index = max(int(np.ceil(q * n - 1e-9)), 1) - 1
    estimates = np.sort(draws, axis=1)[:, index]  # a failure (NaN) sorts after every step
    estimates[np.isnan(estimates)] = np.inf
    # Order statistics, not interpolation: an end beyond the limit (infinite) stays one.
    low = float(np.percentile(estimates, 2.5, method="lower"))
    high = float(np.percentile(estimates, 97.5, method="higher"))
    return [None if np.isinf(low) else low, None if np.isinf(high) else high]
