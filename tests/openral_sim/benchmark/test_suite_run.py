"""A suite's run: rows in order, thresholds per row, speed against a baseline, and a failure that ends the suite."""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from openral_core import BenchmarkRun, EpisodeResult, ROSConfigError, SimEnvironment
from openral_sim import evaluation
from openral_sim.benchmark.rows import SuiteRow
from openral_sim.benchmark.suite_run import ServeOptions, run_suite, worker_processes
from openral_sim.build import EpisodeBatch

ROOT = Path(__file__).resolve().parents[3]
MOCK = SimEnvironment.from_yaml(ROOT / "scenes" / "sim" / "mock_reach.yaml").model_copy(update={"cameras": []})


def _row(n_episodes: int, label: str, **run: Any) -> SuiteRow:
    scene = MOCK.model_copy(update={"n_episodes": n_episodes})
    return SuiteRow(BenchmarkRun(scene="mock_reach.yaml", label=label, **{"skill": "zero", **run}), scene)


def _batch(successes: Sequence[bool]) -> EpisodeBatch:
    episodes = [EpisodeResult(episode_idx=i, seed=i, success=s, steps=5) for i, s in enumerate(successes)]
    return EpisodeBatch(episodes=episodes, tick_ms=[1.0, 2.0], inference_ms=[0.5], env_builds={"here": 1})


class ScriptedEvaluator:
    """Gives each row the next scripted batch, or raises the next scripted exception."""

    ray_address = None
    processes = 2

    def __init__(self, *outcomes: EpisodeBatch | BaseException) -> None:
        self.outcomes = list(outcomes)
        self.warmed: list[evaluation.EpisodeUnit] = []
        self.scheduled: list[tuple[str, int]] = []

    def warm_up(self, unit: evaluation.EpisodeUnit) -> None:
        self.warmed.append(unit)

    def wait_warm(self) -> None:
        pass

    def schedule(self, scene: SimEnvironment, skill_id: str, params: dict[str, Any], n: int) -> list[str]:
        self.scheduled.append((skill_id, n))
        return [skill_id]

    def run(self, units: list[str]) -> EpisodeBatch:
        outcome = self.outcomes.pop(0)
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome


def test_rows_run_in_order_each_against_its_own_threshold_or_the_suites() -> None:
    evaluator = ScriptedEvaluator(_batch([True, False]), _batch([False, False, True]))
    rows = [_row(2, "own", min_success=50.0), _row(3, "suites")]
    progress: list[str] = []
    outcome = run_suite(
        rows, evaluator, started=time.perf_counter(), min_success=40.0, on_row=lambda r: progress.append(r["label"])
    )
    assert evaluator.warmed[0].skill_id == "zero"  # the first row's workers start before the rows are checked
    assert evaluator.scheduled == [("zero", 2), ("zero", 3)]
    own, suites = outcome.results
    assert (own["status"], own["pc_success"], own["min_success"], own["env_builds"]) == ("completed", 50.0, 50.0, 1)
    assert suites["min_success"] == 40.0
    assert outcome.below_min_success == ["suites: 33.3 % < 40 %"]
    assert progress == ["own", "suites"]
    assert outcome.error is None
    assert outcome.not_run == []
    assert own["speedup"] is None  # no baseline: nothing measured to compare with
    assert own["episodes_per_s_per_worker"] == pytest.approx(own["episodes_per_s"] / 2)


def test_an_interrupted_row_ends_the_suite_and_names_the_rows_after_it() -> None:
    interrupt = KeyboardInterrupt()
    evaluator = ScriptedEvaluator(_batch([True]), interrupt)
    rows = [_row(1, "first"), _row(1, "second"), _row(1, "third"), _row(1, "fourth")]
    progress: list[str] = []
    outcome = run_suite(rows, evaluator, started=time.perf_counter(), on_row=lambda r: progress.append(r["label"]))
    assert outcome.error is interrupt
    assert [(r["label"], r["status"]) for r in outcome.results] == [("first", "completed"), ("second", "failed")]
    assert outcome.results[1]["error"] == "KeyboardInterrupt: interrupted"
    assert outcome.not_run == ["third", "fourth"]
    assert progress == ["first"]  # a failed row is no progress line


def test_a_baseline_gives_completed_rows_speedup_and_efficiency() -> None:
    evaluator = ScriptedEvaluator(_batch([True, True]))
    baseline = [{"label": "row", "status": "completed", "seeds": [0, 1], "episodes_per_s": 0.5}]
    outcome = run_suite([_row(2, "row")], evaluator, started=time.perf_counter(), baseline=baseline)
    (row,) = outcome.results
    assert row["speedup"] == pytest.approx(row["episodes_per_s"] / 0.5)
    assert row["efficiency"] == pytest.approx(row["speedup"] / 2)


def test_a_bad_row_or_baseline_is_refused_before_any_episode_runs() -> None:
    evaluator = ScriptedEvaluator()
    with pytest.raises(ROSConfigError, match=r"runs\[1\]\.skill: unknown skill 'randm'"):
        run_suite([_row(1, "a"), _row(1, "b", skill="randm")], evaluator, started=0.0)
    with pytest.raises(ROSConfigError, match="--baseline: no completed row 'a'"):
        run_suite([_row(1, "a")], evaluator, started=0.0, baseline=[])
    assert evaluator.scheduled == []


def test_workers_are_capped_by_the_largest_row_and_the_cpus_and_the_cap_is_said(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(evaluation, "usable_cpus", lambda: 4)
    rows = [_row(3, "a"), _row(6, "b")]
    assert worker_processes(2, rows) == (2, None)
    assert worker_processes(16, rows) == (
        4,
        "--workers 16: starting 4 worker processes (4 CPUs usable here, at most 6 episodes in a row)",
    )


def test_serving_describes_its_batch_as_one_request_per_process_unless_given() -> None:
    assert ServeOptions().described(3) == {"max_batch": 3, "gpus": 0.0}
    assert ServeOptions(max_batch=8, gpus=0.5).described(3) == {"max_batch": 8, "gpus": 0.5}
    assert ServeOptions().described(None) == {"max_batch": None, "gpus": 0.0}  # Ray: one per cluster process
