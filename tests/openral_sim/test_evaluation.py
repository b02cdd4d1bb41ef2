"""Evaluation units: the Wilson interval, splitting, identical outcomes in one process, two workers and Ray, and
workers that build each environment once."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest

from openral_core import ObserverConfig, SimCamera, SimEnvironment
from openral_sim.build import SkillFailed, process_name
from openral_sim.evaluation import (
    EpisodeUnit,
    Evaluator,
    run_units,
    schedule_episodes,
    split_episodes,
    summarize,
    throughput,
    usable_cpus,
    wilson_interval,
    with_observers,
    worker_processes,
)

SCENE = SimEnvironment(
    name="reach", env="mock", task="reach", success_key="is_success", max_steps=25, n_episodes=8, seed=3
)
FILMED = SCENE.model_copy(update={"cameras": [SimCamera(name="top", width=32, height=32)]})
"""The scene with a camera to film."""


def _video_entry(folder: str, episodes: int) -> ObserverConfig:
    return ObserverConfig(id="episode_video", params={"folder": folder, "episodes": episodes, "prefix": "reach"})


def test_wilson_interval_matches_the_formula_and_stays_inside_zero_one() -> None:
    assert wilson_interval(0, 50) == pytest.approx((0.0, 0.071348), abs=1e-6)
    assert wilson_interval(50, 50) == pytest.approx((0.928652, 1.0), abs=1e-6)
    assert wilson_interval(40, 50) == pytest.approx((0.669629, 0.887562), abs=1e-6)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    low, high = wilson_interval(7, 20)
    assert low < 7 / 20 < high


def test_split_covers_every_episode_once_in_order() -> None:
    units = split_episodes(SCENE, "zero", {}, 8, 3)
    covered = [i for u in units for i in range(u.first_episode, u.first_episode + u.n_episodes)]
    assert covered == list(range(8))
    assert len(split_episodes(SCENE, "zero", {}, 2, 5)) == 2


def test_factoring_hands_out_every_episode_once_largest_units_first_and_single_episodes_last() -> None:
    units = schedule_episodes(SCENE, "zero", {}, 48, 2)
    covered = [i for u in units for i in range(u.first_episode, u.first_episode + u.n_episodes)]
    assert covered == list(range(48))
    sizes = [u.n_episodes for u in units]
    assert sizes == sorted(sizes, reverse=True)
    assert sizes[0] == 12  # a quarter of the episodes: half of them shared by the two processes
    assert sizes[-4:] == [1, 1, 1, 1]
    assert len(units) <= 12  # few units: each costs a run's start
    assert [u.n_episodes for u in schedule_episodes(SCENE, "zero", {}, 48, 1)] == [48]
    assert [u.n_episodes for u in schedule_episodes(SCENE, "zero", {}, 3, 16)] == [1, 1, 1]


def test_throughput_has_no_speedup_without_a_measured_one_process_rate() -> None:
    alone = throughput(48, 12.0, 2)
    assert alone == {
        "wall_s": 12.0,
        "episodes_per_s": 4.0,
        "episodes_per_s_per_worker": 2.0,
        "speedup": None,
        "efficiency": None,
    }
    measured = throughput(48, 12.0, 2, one_process_per_s=2.5)
    assert measured["speedup"] == pytest.approx(1.6)
    assert measured["efficiency"] == pytest.approx(0.8)
    assert throughput(48, 12.0, None, one_process_per_s=2.5)["efficiency"] is None  # Ray: processes unknown


def test_one_process_builds_the_environment_once_for_all_its_units_and_rows() -> None:
    with Evaluator() as evaluator:
        first = evaluator.run(split_episodes(SCENE, "random", {}, 8, 4))
        second = evaluator.run(split_episodes(SCENE, "zero", {}, 2, 2))
    assert first.env_builds == {process_name(): 1}
    assert second.env_builds == {process_name(): 0}


@pytest.mark.slow
def test_worker_processes_build_each_environment_once_and_keep_it_for_every_later_unit_and_row() -> None:
    here = run_units(split_episodes(SCENE, "random", {}, 8, 1)).episodes
    with Evaluator(workers=2) as evaluator:
        first = evaluator.run(split_episodes(SCENE, "random", {}, 8, 8))  # one episode a unit
        later_row = SCENE.model_copy(update={"seed": 20})
        second = evaluator.run(split_episodes(later_row, "zero", {}, 6, 6))
    assert [e.outcome() for e in first.episodes] == [e.outcome() for e in here]
    processes = set(first.env_builds) | set(second.env_builds)
    assert 1 <= len(processes) <= 2
    assert process_name() not in processes
    # Every worker built the environment once, whichever units and rows it ran.
    assert [first.env_builds.get(p, 0) + second.env_builds.get(p, 0) for p in processes] == [1] * len(processes)


@pytest.mark.slow
def test_warmed_up_workers_run_their_units_on_the_environment_the_warm_up_built() -> None:
    with Evaluator(workers=2) as evaluator:
        evaluator.warm_up(EpisodeUnit(SCENE, "random", {}))
        batch = evaluator.run(split_episodes(SCENE, "random", {}, 8, 8))
    # The warm-up's build is reported with the worker's first unit, and is the only one.
    assert batch.env_builds
    assert set(batch.env_builds.values()) == {1}
    # A warm-up that cannot build leaves the run to build, and to report what fails.
    with Evaluator(workers=2) as evaluator:
        evaluator.warm_up(EpisodeUnit(SCENE, "randm", {}))
        assert len(evaluator.run(split_episodes(SCENE, "zero", {}, 4, 4)).episodes) == 4


def test_summary_uses_lerobots_names_and_the_interval() -> None:
    batch = run_units(split_episodes(SCENE, "random", {}, 8, 1))
    summary = summarize(batch.episodes, batch)
    n_success = sum(e.success for e in batch.episodes)
    assert summary["n_success"] == n_success
    assert summary["pc_success"] == pytest.approx(100 * n_success / 8)
    low, high = wilson_interval(n_success, 8)
    assert summary["pc_success_ci95"] == pytest.approx([100 * low, 100 * high])
    assert summary["avg_max_reward"] == pytest.approx(sum(e.max_reward for e in batch.episodes) / 8)
    assert summary["tick_ms"]["p50"] <= summary["tick_ms"]["p99"]


@pytest.mark.slow
def test_two_worker_processes_give_the_outcomes_of_one_process() -> None:
    here = run_units(split_episodes(SCENE, "random", {}, 8, 1)).episodes
    workers = run_units(split_episodes(SCENE, "random", {}, 8, 4), workers=2).episodes
    assert [e.outcome() for e in workers] == [e.outcome() for e in here]


@pytest.mark.slow
def test_two_worker_processes_film_through_an_episode_video_entry_only_the_episodes_it_asks_for(tmp_path) -> None:
    here = run_units(split_episodes(FILMED, "random", {}, 8, 1)).episodes
    units = with_observers(split_episodes(FILMED, "random", {}, 8, 4), _video_entry(str(tmp_path), 3))
    assert all(unit.observers == [_video_entry(str(tmp_path), 3)] for unit in units), "plain data for the workers"
    filmed = run_units(units, workers=2).episodes
    assert [e.outcome() for e in filmed] == [e.outcome() for e in here], "filming changes no outcome"
    videos = sorted(tmp_path.iterdir())
    assert [v.name for v in videos] == ["reach_episode0.mp4", "reach_episode1.mp4", "reach_episode2.mp4"]
    assert all(v.stat().st_size > 0 for v in videos)


def test_a_skill_failing_every_step_stops_the_units_with_its_error_here() -> None:
    # The SO-101 expert needs privileged values the mock does not expose.
    with pytest.raises(SkillFailed, match="grasp_pos") as caught:
        run_units(split_episodes(SCENE, "so101_pick_expert", {}, 8, 2))
    # One process stops at the first fault limit, as a single run of every episode would.
    assert [(e.episode_idx, e.ended_by) for e in caught.value.batch.episodes] == [(0, "faults")]


@pytest.mark.slow
def test_a_skill_failing_every_step_in_worker_processes_is_an_error_with_every_units_episodes() -> None:
    with pytest.raises(SkillFailed, match="grasp_pos") as caught:
        run_units(split_episodes(SCENE, "so101_pick_expert", {}, 8, 4), workers=2)
    episodes = caught.value.batch.episodes
    assert [(e.episode_idx, e.ended_by) for e in episodes] == [
        (0, "faults"),
        (2, "faults"),
        (4, "faults"),
        (6, "faults"),
    ]
    assert "episode 0" in str(caught.value)


# Under ``uv run`` Ray would start its workers with ``uv run`` in a packaged copy of the project
# (a fresh venv each); they are on this machine and use this interpreter.
RAY_ENV = {**os.environ, "RAY_ENABLE_UV_RUN_RUNTIME_ENV": "0"}

RAY_RUN = """
import json, ray
from openral_core import ObserverConfig, SimEnvironment
from openral_sim.build import SkillFailed
from openral_sim.evaluation import Evaluator, run_units, split_episodes, with_observers
from openral_sim.worker_environment import thread_report
scene = SimEnvironment.model_validate_json({scene!r})
video = ObserverConfig(id="episode_video", params={{"folder": {videos!r}, "episodes": 2, "prefix": "reach"}})
ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
try:
    batch = run_units(with_observers(split_episodes(scene, "random", {{}}, 8, 4), video), ray_address="local")
    builds = batch.env_builds
    try:
        run_units(split_episodes(scene, "so101_pick_expert", {{}}, 8, 4), ray_address="local")
        failure = None
    except SkillFailed as exc:
        failure = [str(exc), [e.ended_by for e in exc.batch.episodes]]
    threads = Evaluator(ray_address="local").in_worker(thread_report)["variables"]
finally:
    ray.shutdown()
print(json.dumps([[e.outcome() for e in batch.episodes], failure, builds, threads]))
"""


@pytest.mark.slow
@pytest.mark.timeout(600)  # a Ray cluster of its own starts first: tens of seconds on a busy machine
def test_ray_gives_the_outcomes_of_one_process_films_reports_a_failing_skill_and_limits_threads(tmp_path) -> None:
    if importlib.util.find_spec("ray") is None:  # not imported here: Ray installs process-wide handlers
        pytest.skip("needs the 'ray' extra")
    here = run_units(split_episodes(FILMED, "random", {}, 8, 1)).episodes
    # Ray starts its own processes and signal handlers: it runs in a child, not in the test process.
    code = RAY_RUN.format(scene=FILMED.model_dump_json(), videos=str(tmp_path))
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False, env=RAY_ENV
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    on_ray, failure, builds, threads = json.loads(proc.stdout.strip().splitlines()[-1])
    assert on_ray == [e.outcome() for e in here]
    assert sorted(v.name for v in tmp_path.iterdir()) == ["reach_episode0.mp4", "reach_episode1.mp4"]
    assert builds
    assert set(builds.values()) == {1}  # a Ray worker keeps its environment for its next tasks
    # A skill failing on every step is an error on Ray too, with each unit's episode ended by the faults.
    assert failure is not None
    message, ended_by = failure
    assert "grasp_pos" in message
    assert ended_by == ["faults"] * 4
    # A Ray task's worker starts with one thread per library, as a worker process here does.
    assert set(threads.values()) == {"1"}, threads


def test_worker_processes_are_capped_by_the_units_and_the_cpus_this_process_may_use() -> None:
    cpus = usable_cpus()
    assert cpus == len(os.sched_getaffinity(0))
    assert worker_processes(1000, 3) == min(3, cpus)
    assert worker_processes(1000, 10**6) == cpus
    assert worker_processes(1, 10**6) == 1
    assert worker_processes(4, 0) == 1  # at least one


class _RecordingRay:
    """Stands in for the ``ray`` module: remembers what the environment said when it was initialised."""

    def __init__(self) -> None:
        self.uv_runtime_env: list[str | None] = []

    def is_initialized(self) -> bool:
        return False

    def init(self, **_kwargs: object) -> None:
        self.uv_runtime_env.append(os.environ.get("RAY_ENABLE_UV_RUN_RUNTIME_ENV"))

    def remote(self, function: object) -> object:
        return function


@pytest.mark.parametrize(("address", "expected"), [("local", "0"), ("ray://head:10001", None)])
def test_a_local_ray_cluster_runs_its_workers_on_this_interpreter_not_a_fresh_uv_environment(
    monkeypatch: pytest.MonkeyPatch, address: str, expected: str | None
) -> None:
    fake = _RecordingRay()
    monkeypatch.setitem(sys.modules, "ray", fake)
    monkeypatch.setenv("RAY_ENABLE_UV_RUN_RUNTIME_ENV", "unset afterwards")  # so the teardown removes it
    monkeypatch.delenv("RAY_ENABLE_UV_RUN_RUNTIME_ENV")
    evaluator = Evaluator(ray_address=address)
    evaluator.ray()
    assert fake.uv_runtime_env == [expected]
