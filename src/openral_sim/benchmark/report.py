"""The benchmark report: the JSON document, a row's progress line and the rows as a Markdown table."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from openral_sim.benchmark.suite_run import SuiteOutcome
from openral_sim.evaluation import real_time_note


def suite_document(suite: str, outcome: SuiteOutcome, *, wall_s: float, provenance: dict[str, Any]) -> dict[str, Any]:
    """The report of a suite's run; after a failed row it lists the rows that did not run (``not_run``)."""
    document: dict[str, Any] = {
        "suite": suite,
        "results": outcome.results,
        "startup_s": outcome.startup_s,
        "wall_s": wall_s,
        "provenance": provenance,
    }
    if outcome.error is not None:
        document["not_run"] = outcome.not_run
    return document


def table_line(row: dict[str, Any]) -> str:
    """A completed row in one line: success with its interval, episodes, time and episodes per second."""
    low, high = row["pc_success_ci95"]
    return (
        f"{row['label']}: {row['pc_success']:.1f} % [{low:.1f}, {high:.1f}] over {row['n_episodes']} episodes "
        f"in {row['wall_s']:.1f} s ({row['episodes_per_s']:.2f} episodes/s){real_time_note(row)}"
    )


def markdown_table(rows: Sequence[dict[str, Any]], workers: int | None) -> str:
    """The rows as a Markdown table; efficiency reads ``—`` without a baseline to measure it against.

    ``workers`` is the processes the speed-up was reached on (``None`` on Ray). Efficiency is the
    speed-up over the one-worker baseline divided by them: 1.00 is perfect scaling.
    """
    lines = [
        "| scene / skill | episodes | success | 95 % CI | steps to success (p50) | tick p50 / p99 ms "
        "| episodes/s | efficiency (speed-up) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if row["status"] == "failed":
            lines.append(f"| {row['label']} | failed | — | — | — | — | — | — |")
            continue
        low, high = row["pc_success_ci95"]
        steps = row["steps_to_success"]["p50"]
        tick = row["tick_ms"]
        efficiency = "—"
        if row["efficiency"] is not None:
            efficiency = f"{row['efficiency']:.2f} ({row['speedup']:.2f}× on {workers} workers)"
        lines.append(
            f"| {row['label']} | {row['n_episodes']} | {row['pc_success']:.1f} % | {low:.1f}–{high:.1f} % | "
            f"{'—' if steps is None else f'{steps:.0f}'} | {tick['p50']:.2f} / {tick['p99']:.2f} | "
            f"{row['episodes_per_s']:.2f} | {efficiency} |"
        )
    return "\n".join(lines)
