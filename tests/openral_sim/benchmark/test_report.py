"""The report: the document names the rows not run only after a failure; the table shows every row's outcome."""

from __future__ import annotations

from typing import Any

from openral_sim.benchmark.report import markdown_table, suite_document, table_line
from openral_sim.benchmark.suite_run import SuiteOutcome


def _completed(**overrides: Any) -> dict[str, Any]:
    row = {
        "label": "scene/skill",
        "status": "completed",
        "n_episodes": 10,
        "pc_success": 70.0,
        "pc_success_ci95": [39.68, 89.22],
        "steps_to_success": {"mean": 12.4, "p50": 12.0},
        "tick_ms": {"p50": 1.234, "p99": 5.678},
        "wall_s": 4.04,
        "episodes_per_s": 2.475,
        "speedup": None,
        "efficiency": None,
    }
    return {**row, **overrides}


def test_the_table_has_a_line_per_row_and_a_failed_row_has_no_numbers() -> None:
    table = markdown_table([_completed(), {"label": "broken", "status": "failed"}], workers=2)
    header, rule, done, failed = table.splitlines()
    assert header.count("|") == rule.count("|") == done.count("|") == failed.count("|") == 9
    assert done == "| scene/skill | 10 | 70.0 % | 39.7–89.2 % | 12 | 1.23 / 5.68 | 2.48 | — |"
    assert failed == "| broken | failed | — | — | — | — | — | — |"


def test_the_table_shows_efficiency_with_its_speedup_and_workers_and_no_steps_without_a_success() -> None:
    row = _completed(speedup=1.8, efficiency=0.9, steps_to_success={"mean": None, "p50": None})
    line = markdown_table([row], workers=2).splitlines()[-1]
    assert line.endswith("| — | 1.23 / 5.68 | 2.48 | 0.90 (1.80× on 2 workers) |")


def test_a_progress_line_says_success_interval_episodes_and_speed() -> None:
    assert table_line(_completed()) == "scene/skill: 70.0 % [39.7, 89.2] over 10 episodes in 4.0 s (2.48 episodes/s)"


def test_the_document_names_the_rows_not_run_only_after_a_failure() -> None:
    finished = SuiteOutcome(results=[_completed()], startup_s=1.5)
    document = suite_document("tiny", finished, wall_s=6.0, provenance={"workers": 1})
    assert document == {
        "suite": "tiny",
        "results": [_completed()],
        "startup_s": 1.5,
        "wall_s": 6.0,
        "provenance": {"workers": 1},
    }
    failed = SuiteOutcome(results=[], startup_s=1.5, error=RuntimeError("x"), not_run=["later"])
    assert suite_document("tiny", failed, wall_s=6.0, provenance={})["not_run"] == ["later"]
