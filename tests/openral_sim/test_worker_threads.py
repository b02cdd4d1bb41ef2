"""Worker processes start with one thread per numeric library unless asked otherwise, and the report says so."""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from openral_cli.main import cli
from openral_core import SimEnvironment
from openral_rskill.worker_threads import THREADS_PER_WORKER_VARIABLE, threads_per_worker
from openral_sim.benchmark.baseline import Baseline, threads_note
from openral_sim.evaluation import EpisodeUnit, Evaluator, usable_cpus
from openral_sim.worker_environment import LIBRARY_VARIABLES, spawning_with, thread_report, worker_environment

ROOT = Path(__file__).resolve().parents[2]
MOCK_SCENE = ROOT / "scenes" / "sim" / "mock_reach.yaml"
SCENE = SimEnvironment(
    name="reach", env="mock", task="reach", success_key="is_success", max_steps=25, n_episodes=4, seed=3
)
VARIABLES = (THREADS_PER_WORKER_VARIABLE, *LIBRARY_VARIABLES)
OS_THREADS = functools.partial(os.listdir, "/proc/self/task")
"""A process's threads, as Linux lists them (OpenBLAS starts its pool's threads as numpy loads)."""


@pytest.fixture
def unlimited(monkeypatch: pytest.MonkeyPatch) -> None:
    """No thread variable in this process's environment, whatever the machine's shell set."""
    for name in VARIABLES:
        monkeypatch.delenv(name, raising=False)


def test_a_worker_environment_names_every_library_and_no_limit_names_none() -> None:
    assert worker_environment(2) == {
        "OPENRAL_THREADS_PER_WORKER": "2",
        "OMP_NUM_THREADS": "2",
        "OPENBLAS_NUM_THREADS": "2",
        "MKL_NUM_THREADS": "2",
        "VECLIB_MAXIMUM_THREADS": "2",
        "NUMEXPR_NUM_THREADS": "2",
    }
    assert worker_environment(None) == {}


def test_spawning_with_sets_the_variables_inside_and_restores_what_was_there(
    monkeypatch: pytest.MonkeyPatch, unlimited: None
) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    with spawning_with(worker_environment(1)):
        assert {name: os.environ.get(name) for name in VARIABLES} == dict.fromkeys(VARIABLES, "1")
        assert threads_per_worker() == 1
    assert os.environ["OMP_NUM_THREADS"] == "7"
    assert [name for name in VARIABLES if name in os.environ] == ["OMP_NUM_THREADS"]
    assert threads_per_worker() is None


@pytest.mark.parametrize("value", ["0", "-1", "two", ""])
def test_an_allowance_that_is_no_positive_count_is_none(monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.setenv(THREADS_PER_WORKER_VARIABLE, value)
    assert threads_per_worker() is None


@pytest.mark.parametrize(
    ("workers", "ray", "asked", "threads"),
    [(1, None, None, None), (2, None, None, 1), (1, None, 3, 3), (2, None, 0, None), (1, "auto", None, 1)],
)
def test_the_limit_is_one_thread_in_workers_none_in_one_process_here_and_what_was_asked(
    workers: int, ray: str | None, asked: int | None, threads: int | None
) -> None:
    assert Evaluator(workers=workers, ray_address=ray, threads_per_worker=asked).threads == threads


def test_a_negative_thread_count_is_refused() -> None:
    with pytest.raises(ValueError, match="threads_per_worker must be 0 or more, not -1"):
        Evaluator(workers=2, threads_per_worker=-1)


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads in Linux's /proc")
def test_a_worker_process_runs_its_units_with_one_blas_thread_and_unlimited_ones_start_more(unlimited: None) -> None:
    with Evaluator(workers=2) as evaluator:
        evaluator.warm_up(EpisodeUnit(SCENE, "zero", {}))  # the worker has loaded numpy and built the scene
        evaluator.wait_warm()
        report = evaluator.in_worker(thread_report)
        pinned = len(evaluator.in_worker(OS_THREADS))
        assert (
            len(evaluator.run([EpisodeUnit(SCENE, "zero", {}, 0, 2), EpisodeUnit(SCENE, "zero", {}, 2, 2)]).episodes)
            == 4
        )
    assert report["variables"] == dict.fromkeys(VARIABLES, "1")
    assert pinned == 1  # the worker's own thread: OpenBLAS started none
    assert all(name not in os.environ for name in VARIABLES), "this process's environment is restored"
    if usable_cpus() >= 2:
        with Evaluator(workers=2, threads_per_worker=0) as evaluator:
            evaluator.warm_up(EpisodeUnit(SCENE, "zero", {}))
            evaluator.wait_warm()
            assert evaluator.in_worker(thread_report)["variables"] == dict.fromkeys(VARIABLES)
            assert len(evaluator.in_worker(OS_THREADS)) > pinned


TORCH_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"


def test_torch_in_a_worker_process_uses_the_threads_asked_for(unlimited: None) -> None:
    torch = pytest.importorskip("torch", reason=TORCH_REASON)
    with Evaluator(workers=2) as evaluator:
        assert evaluator.in_worker(torch.get_num_threads) == 1
    with Evaluator(workers=1, threads_per_worker=2) as evaluator:  # one worker process, where the count applies
        assert evaluator.in_worker(torch.get_num_threads) == 2


def test_one_process_runs_here_with_the_libraries_as_they_are(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", "5")
    with Evaluator() as evaluator:
        assert evaluator.in_worker(os.getpid) == os.getpid()
        assert evaluator.in_worker(thread_report)["variables"]["OMP_NUM_THREADS"] == "5"


def _suite(tmp_path: Path, episodes: int) -> Path:
    suite = tmp_path / "suite.yaml"
    suite.write_text(
        f"name: threads\nruns:\n  - {{scene: {MOCK_SCENE}, skill: zero, n_episodes: {episodes}}}\n", encoding="utf-8"
    )
    return suite


def test_the_report_records_the_limit_and_what_a_worker_was_told(tmp_path: Path, unlimited: None) -> None:
    out = tmp_path / "one.json"
    args = ["benchmark", "run", "--config", str(_suite(tmp_path, 2)), "--threads-per-worker", "2", "--out", str(out)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    provenance = json.loads(out.read_text())["provenance"]
    assert (provenance["workers"], provenance["threads_per_worker"]) == (1, 2)
    assert provenance["worker_threads"]["variables"] == dict.fromkeys(VARIABLES, "2")
    refused = CliRunner().invoke(cli, [*args[:4], "--threads-per-worker", "-1"])
    assert refused.exit_code == 2
    assert "--threads-per-worker" in refused.output


def test_a_baseline_with_another_thread_limit_is_named() -> None:
    def baseline(threads: int | None) -> Baseline:
        return Baseline({"results": [], "provenance": {"workers": 1, "ray": None, "threads_per_worker": threads}}, True)

    assert threads_note(baseline(1), 1) is None
    assert threads_note(baseline(None), 1) == (
        "--baseline: its run allowed unlimited threads per library, this one 1 thread(s): "
        "speed-ups and efficiency measure both the workers and that difference"
    )
    older = Baseline({"results": [], "provenance": {"workers": 1, "ray": None}}, True)
    assert threads_note(older, None) is None  # one process, unlimited, as every run was before the limit
