"""Evaluation units: the Wilson interval, splitting, and identical outcomes in one process, two workers and Ray."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys

import pytest

from openral_core import SimEnvironment
from openral_sim.build import SkillFailed
from openral_sim.evaluation import run_units, split_episodes, summarize, wilson_interval

SCENE = SimEnvironment(
    name="reach", env="mock", task="reach", success_key="is_success", max_steps=25, n_episodes=8, seed=3
)


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


RAY_RUN = """
import json, ray
from openral_core import SimEnvironment
from openral_sim.build import SkillFailed
from openral_sim.evaluation import run_units, split_episodes
scene = SimEnvironment.model_validate_json({scene!r})
ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
try:
    batch = run_units(split_episodes(scene, "random", {{}}, 8, 4), ray_address="local")
    try:
        run_units(split_episodes(scene, "so101_pick_expert", {{}}, 8, 4), ray_address="local")
        failure = None
    except SkillFailed as exc:
        failure = [str(exc), [e.ended_by for e in exc.batch.episodes]]
finally:
    ray.shutdown()
print(json.dumps([[e.outcome() for e in batch.episodes], failure]))
"""


@pytest.mark.slow
def test_ray_gives_the_outcomes_of_one_process_and_reports_a_failing_skill() -> None:
    if importlib.util.find_spec("ray") is None:  # not imported here: Ray installs process-wide handlers
        pytest.skip("needs the 'ray' extra")
    here = run_units(split_episodes(SCENE, "random", {}, 8, 1)).episodes
    # Ray starts its own processes and signal handlers: it runs in a child, not in the test process.
    code = RAY_RUN.format(scene=SCENE.model_dump_json())
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    on_ray, failure = json.loads(proc.stdout.strip().splitlines()[-1])
    assert on_ray == [e.outcome() for e in here]
    # A skill failing on every step is an error on Ray too, with each unit's episode ended by the faults.
    assert failure is not None
    message, ended_by = failure
    assert "grasp_pos" in message
    assert ended_by == ["faults"] * 4
