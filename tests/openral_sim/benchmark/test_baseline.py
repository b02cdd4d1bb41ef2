"""The baseline: a speed reference when it is a one-process run, a paired comparison when its rows pair."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from openral_core import BenchmarkRun, ROSConfigError, SimEnvironment
from openral_sim.benchmark.baseline import Baseline, check_baseline, load_baseline, pairing_problem, references
from openral_sim.benchmark.rows import SuiteRow

ROOT = Path(__file__).resolve().parents[3]
SCENE = SimEnvironment.from_yaml(ROOT / "scenes" / "sim" / "mock_reach.yaml").model_copy(
    update={"n_episodes": 4, "seed": 2}
)
ROW = SuiteRow(BenchmarkRun(scene="mock_reach.yaml", skill="zero"), SCENE)


def _report(tmp_path: Path, results: list[dict[str, Any]], **provenance: Any) -> Path:
    path = tmp_path / "base.json"
    document = {"results": results, "provenance": {"workers": 1, "ray": None, **provenance}}
    path.write_text(json.dumps(document), encoding="utf-8")
    return path


def test_a_one_process_reports_rows_are_the_baseline(tmp_path: Path) -> None:
    rows = [{"label": "a", "scene": "reach", "status": "completed", "episodes": [{"seed": 0, "success": True}]}]
    baseline = load_baseline(_report(tmp_path, rows))
    assert baseline.rows == rows
    assert baseline.one_process


@pytest.mark.parametrize(("workers", "ray"), [(2, None), (1, "auto")])
def test_a_report_of_several_processes_loads_as_no_speed_reference(
    tmp_path: Path, workers: int, ray: str | None
) -> None:
    assert not load_baseline(_report(tmp_path, [], workers=workers, ray=ray)).one_process


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("{not json", "not a benchmark report"),
        ('{"results": []}', "not a benchmark report: no provenance"),
        ('{"provenance": {"workers": 1, "ray": null}}', "not a benchmark report with per-episode seeds"),
        (
            '{"provenance": {"workers": 1, "ray": null}, "results": [{"status": "completed", "scene": "x", '
            '"episodes": [{"success": true}]}]}',
            "not a benchmark report with per-episode seeds",  # refused now, not after the run
        ),
    ],
)
def test_anything_but_a_report_is_refused_naming_the_option(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "base.json"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ROSConfigError, match=message) as caught:
        load_baseline(path)
    assert caught.value.field == "--baseline"


def test_a_missing_file_is_refused_naming_the_option(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError) as caught:
        load_baseline(tmp_path / "none.json")
    assert caught.value.field == "--baseline"


def test_each_row_is_measured_against_the_baselines_row_of_its_label_and_seeds() -> None:
    baseline = [
        {"label": "mock_reach/zero", "status": "completed", "seeds": [2, 5], "episodes_per_s": 4},
        {"label": "other", "status": "completed", "seeds": [0, 0], "episodes_per_s": 9.0},
    ]
    assert references(baseline, [ROW]) == {"mock_reach/zero": 4.0}


@pytest.mark.parametrize(
    "reference",
    [
        {"label": "mock_reach/zero", "status": "completed", "seeds": [0, 3], "episodes_per_s": 4.0},  # other seeds
        {"label": "mock_reach/zero", "status": "failed", "seeds": [2, 5], "episodes_per_s": 4.0},
        {"label": "mock_reach/zero", "status": "completed", "seeds": [2, 5], "episodes_per_s": 0.0},
        {"label": "mock_reach/other", "status": "completed", "seeds": [2, 5], "episodes_per_s": 4.0},
    ],
)
def test_a_row_the_baseline_did_not_complete_alike_is_refused(reference: dict[str, Any]) -> None:
    with pytest.raises(ROSConfigError, match=r"no completed row 'mock_reach/zero' with seeds \[2, 5\]") as caught:
        references([reference], [ROW])
    assert caught.value.field == "--baseline"


def _completed(**change: Any) -> dict[str, Any]:
    return {**ROW.head(), "status": "completed", "episodes_per_s": 4.0, **change}


def test_a_baseline_of_the_same_scenes_and_seeds_pairs() -> None:
    baseline = Baseline({"results": [_completed(skill="random", label="other")]}, one_process=False)
    assert pairing_problem(baseline, [ROW]) is None
    assert check_baseline(baseline, [ROW]) is True


@pytest.mark.parametrize(
    ("change", "words"),
    [({"seeds": [0, 3]}, "seeds"), ({"env_id": "far"}, "env_id"), ({"scene": "other"}, "0 completed rows")],
)
def test_an_unpairable_baseline_is_refused_unless_it_is_a_speed_reference(change: dict[str, Any], words: str) -> None:
    document = {"results": [_completed(**change)]}
    assert words in (pairing_problem(Baseline(document, one_process=False), [ROW]) or "")
    with pytest.raises(ROSConfigError, match="neither a --workers 1 run") as caught:
        check_baseline(Baseline(document, one_process=False), [ROW])
    assert caught.value.field == "--baseline"
    assert check_baseline(Baseline(document, one_process=True), [ROW]) is False


def test_a_suite_with_two_rows_of_one_scene_does_not_pair() -> None:
    baseline = Baseline({"results": [_completed()]}, one_process=True)
    assert "more than one row" in (pairing_problem(baseline, [ROW, ROW]) or "")
