"""Building a sim evaluation: every name and parameter checked before an episode runs, errors naming their field."""

from __future__ import annotations

import pickle
from typing import Any

import pytest

from openral_core import ROSConfigError, ROSDependencyMissing, RSkillState, SimEnvironment
from openral_sim import build
from openral_sim.build import (
    EpisodeBatch,
    SimCache,
    SkillFailed,
    SkillFields,
    build_sim_runner,
    check_evaluation,
    process_name,
    run_episodes,
)


def _scene(**update: Any) -> SimEnvironment:
    values: dict[str, Any] = {
        "name": "reach",
        "env": "mock",
        "task": "reach the target",
        "max_steps": 10,
        "n_episodes": 1,
    }
    values.update(update)
    return SimEnvironment(**values)


def test_a_suite_rows_skill_and_its_parameters_are_named_as_the_rows_fields() -> None:
    fields = SkillFields.of_row(1)
    with pytest.raises(ROSConfigError, match="did you mean 'random'") as unknown:
        check_evaluation(_scene(), "randm", fields=fields)
    assert unknown.value.field == "runs[1].skill"
    with pytest.raises(ROSConfigError, match="sede") as bad_key:
        check_evaluation(_scene(), "random", {"sede": 1}, fields=fields)
    assert bad_key.value.field == "runs[1].skill_params.sede"
    with pytest.raises(ROSConfigError, match="env: unknown simulation environment 'mokc'") as bad_env:
        check_evaluation(_scene(env="mokc"), "random", fields=fields)
    assert bad_env.value.field == "runs[1].scene"


def test_sim_run_names_its_options() -> None:
    with pytest.raises(ROSConfigError) as bad_key:
        build_sim_runner(_scene(), "random", {"sede": 1})
    assert bad_key.value.field == "--skill-params.sede"


def test_the_environment_is_built_once_per_scene_and_a_good_row_passes() -> None:
    spec = check_evaluation(_scene(), "mock_reach_expert")
    assert spec.action_names == ("dx", "dy")
    # Given the spec of the same scene, the next row's skill is checked against it without an env.
    assert check_evaluation(_scene(env="no-such-env"), "zero", spec=spec) is spec


def test_a_skill_failure_survives_the_trip_back_from_a_worker_process() -> None:
    batch = EpisodeBatch(episodes=[], failure="skill 'x' failed")
    error = pickle.loads(pickle.dumps(SkillFailed("skill 'x' failed", batch=batch)))
    assert str(error) == "skill 'x' failed"
    assert error.batch == batch


def test_a_simulator_missing_here_is_left_to_the_cluster_but_the_skill_name_is_still_checked(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def missing(scene: SimEnvironment) -> Any:
        raise ROSDependencyMissing("mujoco", extra="twin", needed_for="the scene")

    monkeypatch.setattr(build, "make_env", missing)
    with pytest.raises(ROSDependencyMissing):
        check_evaluation(_scene(), "zero")  # the episodes would run here: refused now
    assert check_evaluation(_scene(), "zero", simulator_elsewhere=True) is None
    with pytest.raises(ROSConfigError) as unknown:
        check_evaluation(_scene(), "zeroo", fields=SkillFields.of_row(0), simulator_elsewhere=True)
    assert unknown.value.field == "runs[0].skill"


def test_checking_builds_the_scenes_observers_without_opening_anything(tmp_path) -> None:
    pytest.importorskip("pyarrow", reason="needs the 'dataset' extra")
    watched = _scene(
        cameras=[{"name": "top", "width": 16, "height": 16}],
        observers=[
            {"id": "lerobot_dataset", "params": {"root": str(tmp_path / "ds")}},
            {"id": "episode_video", "params": {"folder": str(tmp_path / "videos")}},
        ],
    )
    assert check_evaluation(watched, "zero") is not None
    assert list(tmp_path.iterdir()) == [], "built and closed: no dataset folder, no video folder"
    with pytest.raises(ROSConfigError, match="did you mean 'episode_video'") as unknown:
        check_evaluation(_scene(observers=[{"id": "episode_vide"}]), "zero")
    assert unknown.value.field == "observers[0].id"
    with pytest.raises(ROSConfigError, match="renders no camera"):
        check_evaluation(_scene(observers=[{"id": "episode_video", "params": {"folder": str(tmp_path)}}]), "zero")
    outside = {"folder": str(tmp_path / "videos"), "prefix": "../../elsewhere"}
    with pytest.raises(ROSConfigError, match="prefix"):
        check_evaluation(
            _scene(cameras=watched.cameras, observers=[{"id": "episode_video", "params": outside}]), "zero"
        )
    assert list(tmp_path.iterdir()) == []


def test_a_cache_runs_slices_on_one_environment_with_the_outcomes_of_a_fresh_run() -> None:
    scene = _scene(n_episodes=6, max_steps=25, seed=7)
    fresh = run_episodes(scene, "random")
    cache = SimCache()
    try:
        head = cache.run(scene, "random", first_episode=0, n_episodes=4)
        tail = cache.run(scene, "random", first_episode=4, n_episodes=2)
        again = cache.run(scene, "random", first_episode=1, n_episodes=1)
    finally:
        cache.close()
    assert [e.outcome() for e in head.episodes + tail.episodes] == [e.outcome() for e in fresh.episodes]
    assert [e.outcome() for e in again.episodes] == [fresh.episodes[1].outcome()]
    assert cache.envs_built == 1
    assert head.env_builds == {process_name(): 1}
    assert tail.env_builds == again.env_builds == {process_name(): 0}
    assert fresh.env_builds == {process_name(): 1}


def test_a_cache_lets_a_latched_skill_go_and_keeps_the_environment() -> None:
    # The SO-101 expert needs privileged values the mock does not expose: its step latches an error.
    scene = _scene(n_episodes=2)
    cache = SimCache()
    try:
        for _ in range(2):
            with pytest.raises(SkillFailed, match="grasp_pos") as caught:
                cache.run(scene, "so101_pick_expert")
            assert [e.ended_by for e in caught.value.batch.episodes] == ["faults"]
        _, skill = cache.prepare(scene, "so101_pick_expert")
        assert skill.state is RSkillState.ACTIVE  # built afresh, not the latched one
        assert len(cache.run(scene, "zero").episodes) == 2
        assert cache.envs_built == 1
    finally:
        cache.close()


def test_a_cache_builds_another_scenes_environment_and_runs_the_first_again_on_a_new_one() -> None:
    cache = SimCache()
    try:
        first, _ = cache.prepare(_scene(), "zero")
        other, _ = cache.prepare(_scene(env_kwargs={"step_size": 0.1}), "zero")
        assert other is not first
        # Another episode count or seed is the same environment.
        assert cache.prepare(_scene(env_kwargs={"step_size": 0.1}, n_episodes=5, seed=9), "zero")[0] is other
        assert cache.prepare(_scene(), "zero")[0] not in (first, other)
        assert cache.envs_built == 3
    finally:
        cache.close()
