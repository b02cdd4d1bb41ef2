"""LIBERO-Pro's perturbed suites as ``libero`` scenes, and LIBERO's two step-limit conventions."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
import pytest

from openral_core import PrivilegedState, ROSConfigError, SimEnvironment, WorldState

pytest.importorskip("libero.libero", reason="needs the 'libero' extra")

from libero.libero import benchmark

from openral_sim.envs.libero import (
    LANGUAGE_PERTURBATIONS,
    PERTURBATIONS,
    PRO_SUITES,
    SUITES,
    LiberoEnv,
    base_suite,
    episode_limit,
    perturbation,
    suite_task,
)
from openral_sim.skills.libero_expert import LiberoExpert

ROOT = Path(__file__).resolve().parents[2]
SCENES = ROOT / "scenes" / "sim"

LENGTHS = {
    "libero_spatial": {"lerobot": 280, "openpi": 220},
    "libero_object": {"lerobot": 280, "openpi": 280},
    "libero_goal": {"lerobot": 300, "openpi": 300},
    "libero_10": {"lerobot": 520, "openpi": 520},
    "libero_90": {"lerobot": 400, "openpi": 400},
}
"""LeRobot's ``TASK_SUITE_MAX_STEPS`` and openpi's ``examples/libero/main.py``, written out by hand."""

BASE_SCENES = {
    "libero_spatial": "libero_spatial",
    "libero_object": "libero_object",
    "libero_goal": "libero_goal_bowl_on_plate",
    "libero_10": "libero_10",
}
"""The scene of each base suite that its LIBERO-Pro scenes perturb (the same task)."""


def pro_scene(suite: str) -> SimEnvironment:
    """The shipped scene of ``suite``: its base scene's file name with the perturbation appended."""
    return SimEnvironment.from_yaml(SCENES / f"{BASE_SCENES[PRO_SUITES[suite]]}_{perturbation(suite)}.yaml")


def test_every_pro_suite_is_registered_with_the_tasks_of_the_suite_it_perturbs() -> None:
    registered = benchmark.get_benchmark_dict()
    with contextlib.redirect_stdout(io.StringIO()):
        for suite, base in PRO_SUITES.items():
            perturbed, original = registered[suite](), registered[base]()
            assert perturbed.get_task_names() == original.get_task_names(), suite
            assert perturbed.n_tasks == SUITES[suite] == 10
    assert {perturbation(suite) for suite in PRO_SUITES} == set(PERTURBATIONS)
    assert perturbation("libero_spatial") is None


@pytest.mark.parametrize("suite", sorted(PRO_SUITES))
def test_a_pro_scene_names_its_suite_the_base_task_and_the_instruction_it_is_given(suite: str) -> None:
    scene = pro_scene(suite)
    base = SimEnvironment.from_yaml(SCENES / f"{BASE_SCENES[PRO_SUITES[suite]]}.yaml")
    assert scene.env_id == suite
    assert scene.env_kwargs == {**base.env_kwargs, "step_limit": "lerobot"}
    assert scene.max_steps == base.max_steps == LENGTHS[PRO_SUITES[suite]]["lerobot"]
    _, instruction, init_states = suite_task(suite, scene.env_kwargs["task_index"])
    assert scene.task == instruction
    # The language perturbations change the words the policy is given; the others keep the base task's.
    assert (scene.task != base.task) == (perturbation(suite) in LANGUAGE_PERTURBATIONS), scene.task
    assert len(init_states) == 50


@pytest.mark.parametrize("suite", sorted(SUITES))
def test_each_convention_gives_the_length_of_the_suite_a_task_belongs_to(suite: str) -> None:
    for convention in ("lerobot", "openpi"):
        assert episode_limit(suite, convention) == LENGTHS[base_suite(suite)][convention]
    assert episode_limit(suite, "scene") is None


def test_a_pro_suite_takes_its_base_suites_lengths() -> None:
    assert episode_limit("libero_spatial_swap", "openpi") == 220
    assert episode_limit("libero_10_lan", "lerobot") == 520


def test_an_unknown_convention_is_refused_naming_the_field_and_the_choices() -> None:
    scene = pro_scene("libero_spatial_swap")
    bad = scene.model_copy(update={"env_kwargs": {**scene.env_kwargs, "step_limit": "openvla"}})
    with pytest.raises(ROSConfigError) as refused:
        LiberoEnv.from_scene(bad)
    assert refused.value.field == "env_kwargs.step_limit"
    assert all(choice in str(refused.value) for choice in ("'scene'", "'lerobot'", "'openpi'"))


def test_a_pro_scene_shorter_than_its_convention_is_refused() -> None:
    scene = pro_scene("libero_spatial_lan").model_copy(update={"max_steps": 250})
    with pytest.raises(ROSConfigError) as refused:
        LiberoEnv.from_scene(scene)
    assert refused.value.field == "max_steps"
    assert "280" in str(refused.value)


def test_a_registered_suite_without_files_is_refused_saying_so() -> None:
    scene = pro_scene("libero_goal_swap").model_copy(update={"env_id": "libero_goal_env"})
    with pytest.raises(ROSConfigError, match="ships no problem files or initial states") as refused:
        LiberoEnv.from_scene(scene)
    assert refused.value.field == "env_id"


def expert_episode(env: LiberoEnv, seed: int) -> tuple[dict[str, list[float]], int | None]:
    """The first observation's privileged values and the step the expert succeeded at (``None``: not in time)."""
    skill = LiberoExpert.from_config({}, robot=env.spec.action_manifest("panda"), rate_hz=20.0)
    skill.configure()
    skill.activate()
    skill.reset(seed=seed)
    observation = env.reset(seed)
    first = dict(observation.privileged)
    assert env.step_limit is not None
    for step_idx in range(1, env.step_limit + 1):
        world = WorldState(stamp_ns=step_idx, privileged=PrivilegedState(values=observation.privileged))
        step = env.step(np.asarray(skill.step(world).first))
        observation = step.observation
        if observation.info["is_success"]:
            return first, step_idx
        if step.truncated:
            break
    return first, None


@pytest.mark.slow
def test_the_expert_solves_a_swapped_layout_that_differs_from_the_base_tasks() -> None:
    swapped = LiberoEnv.from_scene(pro_scene("libero_spatial_swap").model_copy(update={"cameras": []}))
    base_scene = SimEnvironment.from_yaml(SCENES / "libero_spatial.yaml").model_copy(update={"cameras": []})
    base = LiberoEnv.from_scene(base_scene)
    try:
        start, solved_at = expert_episode(swapped, 0)
        base_start = base.reset(0).privileged
    finally:
        swapped.close()
        base.close()
    assert solved_at is not None
    # The plate and the cookie box exchanged regions: each starts near where the other did in the base task.
    plate, box = np.asarray(start["plate_1_pos"][:2]), np.asarray(start["cookies_1_pos"][:2])
    base_plate, base_box = np.asarray(base_start["plate_1_pos"][:2]), np.asarray(base_start["cookies_1_pos"][:2])
    assert np.linalg.norm(plate - base_plate) > 0.1
    assert np.linalg.norm(plate - base_box) < np.linalg.norm(plate - base_plate)
    assert np.linalg.norm(box - base_plate) < np.linalg.norm(box - base_box)
