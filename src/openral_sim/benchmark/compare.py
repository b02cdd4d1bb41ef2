"""Two benchmark reports compared row by row on the same seeds: success, its paired interval, McNemar, time.

A row of A and a row of B are paired by scene; their episodes by seed. Rows that cannot be paired
(a scene only one report ran, other seeds, another environment) are refused with what differs,
never silently dropped: an unpaired comparison is not the comparison asked for. For each pair:

* success of A and B, B − A in percentage points with Newcombe's paired 95 % interval, the
  discordant pairs and the exact McNemar p (:mod:`openral_sim.benchmark.paired`);
* steps to success on the seeds both solved: the mean of B − A, a paired bootstrap 95 % interval
  (seeded, so a comparison prints the same numbers every time) and the exact sign test;
* each smoothness metric (:mod:`openral_sim.smoothness`) the same way, on the seeds where both
  episodes have it (``None``: a report written before episodes recorded smoothness, or no seed
  with a value in both).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from openral_core import ROSConfigError
from openral_core.config_files import read_config_file
from openral_sim.benchmark.paired import PairedTable, mcnemar_exact_p, newcombe_paired_interval
from openral_sim.smoothness import METRICS

SUCCESS_INTERVAL: Final = "newcombe_paired_method_10"
STEPS_INTERVAL: Final = "paired_bootstrap_percentile"
BOOTSTRAP_RESAMPLES: Final = 4000
BOOTSTRAP_SEED: Final = 0
PAIRED_FIELDS: Final = ("env", "env_id")
"""What a row of A and its row of B must share besides the scene and the seeds."""
LIMIT_FIELDS: Final = ("max_steps", "step_limit")
"""The episode length and its named convention: compared where both rows carry them (older reports do not)."""
MAX_REPORT_BYTES: Final = 256 * 2**20
"""A report of many thousand episodes is a few megabytes; far past this it is not one."""


def load_report(path: Path, *, field: str) -> dict[str, Any]:
    """A ``benchmark run --out`` report, with every completed row's episodes (seed and outcome).

    Raises:
        ROSConfigError: Missing, not a regular file, over :data:`MAX_REPORT_BYTES`, not JSON, or
            without per-episode seeds (one line, naming ``field``).
    """
    text = read_config_file(path, field=field, max_bytes=MAX_REPORT_BYTES)
    try:
        document = json.loads(text)
        rows = document["results"]
        for row in rows:
            if row.get("status") == "completed":
                str(row["scene"])
                for episode in row["episodes"]:
                    int(episode["seed"]), bool(episode["success"])
                    steps = episode.get("steps_to_success")
                    if steps is not None and not isinstance(steps, int):
                        raise TypeError(f"steps_to_success {steps!r} is not a whole number")
                    _check_smoothness(episode.get("smoothness"))
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ROSConfigError(
            f"{path} is not a benchmark report with per-episode seeds and outcomes ({type(exc).__name__}: {exc})",
            field=field,
            hint="write one with: openral benchmark run --config SUITE --out FILE",
        ) from exc
    return dict(document)


def _check_smoothness(smoothness: Any) -> None:
    """An episode's smoothness, when it has one, is numbers (or ``None``) by metric.

    Raises:
        TypeError: It is not.
    """
    if smoothness is None:
        return
    if not isinstance(smoothness, Mapping):
        raise TypeError(f"smoothness {smoothness!r} is not an object")
    for name in METRICS:
        value = smoothness.get(name)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)):
            raise TypeError(f"smoothness.{name} {value!r} is not a number")


def compare_reports(a: Mapping[str, Any], b: Mapping[str, Any]) -> dict[str, Any]:
    """Every scene both reports completed, A against B on the same seeds.

    Raises:
        ROSConfigError: A scene only one report completed, or paired rows that differ (environment,
            seeds), named.
    """
    rows_a, rows_b = _completed_by_scene(a, "A"), _completed_by_scene(b, "B")
    only = sorted(set(rows_a) ^ set(rows_b))
    if only:
        scene = only[0]
        side, other = ("A", "B") if scene in rows_a else ("B", "A")
        raise ROSConfigError(
            f"scene {scene!r} is in {side}'s report and not in {other}'s: every row must have its pair",
            field="B" if side == "A" else "A",
            hint="run the same suite (scenes, seeds) for both policies",
        )
    return {
        "a": _identity(a),
        "b": _identity(b),
        "success_interval": SUCCESS_INTERVAL,
        "steps_interval": STEPS_INTERVAL,
        "rows": [compare_rows(rows_a[scene], rows_b[scene]) for scene in sorted(rows_a)],
    }


def compare_rows(a: Mapping[str, Any], b: Mapping[str, Any]) -> dict[str, Any]:
    """One scene: A's row and B's, their episodes paired by seed.

    Raises:
        ROSConfigError: The rows differ in environment, seeds or episode length.
    """
    scene = a["scene"]
    mismatch = timing_problem(a, b)
    if mismatch is not None:
        raise ROSConfigError(f"scene {scene!r}: {mismatch}", field=f"B.results[{scene}].timing")
    shared_limits = tuple(key for key in LIMIT_FIELDS if key in a and key in b)
    for key in (*PAIRED_FIELDS, "seeds", *shared_limits):
        if a.get(key) != b.get(key):
            raise ROSConfigError(
                f"scene {scene!r}: A's row has {key} {a.get(key)!r} and B's {b.get(key)!r}; paired rows must agree",
                field=f"B.results[{scene}].{key}",
            )
    episodes_a, episodes_b = _by_seed(a, "A"), _by_seed(b, "B")
    if set(episodes_a) != set(episodes_b):
        unpaired = sorted(set(episodes_a) ^ set(episodes_b))
        raise ROSConfigError(
            f"scene {scene!r}: {len(unpaired)} seed(s) ran in only one report (first: {unpaired[0]})",
            field=f"B.results[{scene}].episodes",
        )
    seeds = sorted(episodes_a)
    table = PairedTable.of(
        [bool(episodes_a[s]["success"]) for s in seeds], [bool(episodes_b[s]["success"]) for s in seeds]
    )
    low, high = newcombe_paired_interval(table)
    return {
        "scene": scene,
        "a": a.get("label"),
        "b": b.get("label"),
        "n_pairs": table.n,
        "pc_success_a": 100.0 * table.rate_a,
        "pc_success_b": 100.0 * table.rate_b,
        "difference_pp": 100.0 * (table.rate_b - table.rate_a),
        "difference_pp_ci95": [100.0 * low, 100.0 * high],
        "discordant": {"only_a": table.only_a, "only_b": table.only_b},
        "mcnemar_p": mcnemar_exact_p(table),
        "time_to_success_a": a.get("time_to_success"),
        "time_to_success_b": b.get("time_to_success"),
        "steps_to_success": paired_steps(
            [episodes_a[s].get("steps_to_success") for s in seeds],
            [episodes_b[s].get("steps_to_success") for s in seeds],
        ),
        "smoothness": paired_smoothness([episodes_a[s] for s in seeds], [episodes_b[s] for s in seeds]),
    }


def row_timing(row: Mapping[str, Any]) -> str:
    """How a report's row timed inference (``virtual``, ``measured`` or ``real``); an older row is virtual."""
    return str(row.get("timing") or "virtual")


def timing_problem(a: Mapping[str, Any], b: Mapping[str, Any], names: tuple[str, str] = ("A", "B")) -> str | None:
    """Why rows A and B cannot pair for how they timed inference (one line), or ``None`` when they agree.

    A measured row's outcomes depend on the machine it ran on; a virtual row's on the seeds alone.
    """
    timing_a, timing_b = row_timing(a), row_timing(b)
    if timing_a == timing_b:
        return None
    return (
        f"{names[0]}'s row ran with {timing_a} latency and {names[1]}'s with {timing_b}; paired rows must agree "
        "(a measured row's outcomes depend on the machine, a virtual row's on the seeds)"
    )


def paired_steps(a: Sequence[int | None], b: Sequence[int | None]) -> dict[str, Any]:
    """Steps to success on the seeds both solved: B − A's mean, its paired bootstrap interval, the sign test."""
    differences = paired_differences(a, b)
    if differences is None:
        return {"n_both_succeeded": 0, "mean_difference": None, "mean_difference_ci95": None, "sign_test_p": None}
    return {
        "n_both_succeeded": differences["n_pairs"],
        "mean_difference": differences["mean_difference"],
        "mean_difference_ci95": differences["mean_difference_ci95"],
        "b_faster": differences["b_lower"],
        "b_slower": differences["b_higher"],
        "sign_test_p": differences["sign_test_p"],
    }


def paired_smoothness(a: Sequence[Mapping[str, Any]], b: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """Each smoothness metric of the paired episodes ``a`` and ``b`` (:func:`paired_differences`).

    ``None`` when either side's episodes did not record smoothness (a report of an earlier version).
    """
    smooth_a, smooth_b = [e.get("smoothness") for e in a], [e.get("smoothness") for e in b]
    if not any(smooth_a) or not any(smooth_b):
        return None
    return {
        name: paired_differences(
            [None if s is None else s.get(name) for s in smooth_a],
            [None if s is None else s.get(name) for s in smooth_b],
        )
        for name in METRICS
    }


def paired_differences(a: Sequence[float | None], b: Sequence[float | None]) -> dict[str, Any] | None:
    """B − A on the pairs where both have a value: means, the mean difference, its paired bootstrap interval, sign test.

    The bootstrap resamples the pairs (seeded, :data:`BOOTSTRAP_RESAMPLES`); the exact sign test
    counts the pairs where B is lower and higher (ties carry no sign). ``None`` without a pair.
    """
    pairs = np.array([(x, y) for x, y in zip(a, b, strict=True) if x is not None and y is not None], dtype=float)
    n = len(pairs)
    if n == 0:
        return None
    differences = pairs[:, 1] - pairs[:, 0]
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    means = differences[rng.integers(0, n, size=(BOOTSTRAP_RESAMPLES, n))].mean(axis=1)
    lower, higher = int((differences < 0).sum()), int((differences > 0).sum())
    return {
        "n_pairs": n,
        "mean_a": float(pairs[:, 0].mean()),
        "mean_b": float(pairs[:, 1].mean()),
        "mean_difference": float(differences.mean()),
        "mean_difference_ci95": [float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))],
        "b_lower": lower,
        "b_higher": higher,
        "sign_test_p": mcnemar_exact_p(PairedTable(both=0, only_a=higher, only_b=lower, neither=0)),
    }


def comparison_lines(comparison: Mapping[str, Any]) -> list[str]:
    """One line per scene for a terminal."""
    lines = [f"A: {comparison['a']}   B: {comparison['b']}   (B − A; success interval: Newcombe, paired)"]
    for row in comparison["rows"]:
        low, high = row["difference_pp_ci95"]
        steps = row["steps_to_success"]
        timing = (
            f"steps to success B − A {steps['mean_difference']:+.1f} (95 % CI {steps['mean_difference_ci95'][0]:+.1f} "
            f"to {steps['mean_difference_ci95'][1]:+.1f}, {steps['n_both_succeeded']} seeds both solved)"
            if steps["mean_difference"] is not None
            else "no seed both solved"
        )
        lines.append(
            f"{row['scene']}: {row['pc_success_a']:.1f} % → {row['pc_success_b']:.1f} %, "
            f"{row['difference_pp']:+.1f} pp (95 % CI {low:+.1f} to {high:+.1f}), "
            f"McNemar p {_p(row['mcnemar_p'])} ({row['discordant']['only_a']} only A, "
            f"{row['discordant']['only_b']} only B of {row['n_pairs']}); {timing}"
        )
        lines.append(f"  smoothness B − A: {_smoothness_text(row.get('smoothness'))}")
    return lines


def _smoothness_text(smoothness: Mapping[str, Any] | None) -> str:
    if smoothness is None:
        return "unavailable (a report without per-episode smoothness)"
    parts = []
    for name, (label, unit) in METRICS.items():
        paired = smoothness.get(name)
        if paired is None:
            continue
        low, high = paired["mean_difference_ci95"]
        parts.append(f"{label} {paired['mean_difference']:+.3g} {unit} ({low:+.3g} to {high:+.3g})")
    return "; ".join(parts) or "no seed with a value in both"


def _p(value: float) -> str:
    return f"{value:.2g}" if value < 0.01 else f"{value:.3f}"


def _by_seed(row: Mapping[str, Any], side: str) -> dict[int, Mapping[str, Any]]:
    """A row's episodes by seed; a seed run twice cannot be paired."""
    episodes = {int(e["seed"]): e for e in row["episodes"]}
    if len(episodes) != len(row["episodes"]):
        raise ROSConfigError(
            f"scene {row['scene']!r}: {side}'s row runs a seed more than once; episodes pair by seed",
            field=f"{side}.results[{row['scene']}].episodes",
        )
    return episodes


def _completed_by_scene(document: Mapping[str, Any], side: str) -> dict[str, Mapping[str, Any]]:
    rows: dict[str, Mapping[str, Any]] = {}
    for row in document.get("results", []):
        if row.get("status") != "completed":
            continue
        scene = str(row["scene"])
        if scene in rows:
            raise ROSConfigError(
                f"{side}'s report has two completed rows of scene {scene!r}; compare reports of one policy each",
                field=side,
            )
        rows[scene] = row
    return rows


def _identity(document: Mapping[str, Any]) -> dict[str, Any]:
    """Which run a report is: its suite and the skills of its rows."""
    skills = sorted({str(row.get("skill")) for row in document.get("results", [])})
    return {"suite": document.get("suite"), "skills": skills}
