"""The ``libero`` scene options that score a policy as vla-eval (and openpi's example) do: gripper sign, step limit."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from openral_core import ROSConfigError, SimEnvironment

pytest.importorskip("libero.libero", reason="needs the 'libero' extra")

from openral_sim.envs.libero import MAX_STEPS, OPENPI_MAX_STEPS, LiberoEnv

ROOT = Path(__file__).resolve().parents[2]
SPATIAL = ROOT / "scenes" / "sim" / "libero_spatial.yaml"


def spatial(**env_kwargs: object) -> SimEnvironment:
    scene = SimEnvironment.from_yaml(SPATIAL)
    return scene.model_copy(update={"env_kwargs": {**scene.env_kwargs, **env_kwargs}, "cameras": []})


@pytest.fixture(scope="module")
def openpi_style() -> Iterator[LiberoEnv]:
    env = LiberoEnv.from_scene(spatial(gripper="sign", step_limit="openpi"))
    yield env
    env.close()


def test_the_protocols_lengths_differ_only_for_libero_spatial() -> None:
    assert {suite for suite in MAX_STEPS if MAX_STEPS[suite] != OPENPI_MAX_STEPS[suite]} == {"libero_spatial"}
    assert OPENPI_MAX_STEPS["libero_spatial"] == 220


def fingers(env: LiberoEnv, gripper: float) -> np.ndarray:
    """The finger joints after five steps of ``gripper`` from seed 0's start (fingers open)."""
    env.reset(0)
    for _ in range(5):
        state = env.step(np.array([0, 0, 0, 0, 0, 0, gripper])).observation.state
    return np.asarray(state[6:])


def test_sign_closes_on_a_zero_command(openpi_style: LiberoEnv) -> None:
    np.testing.assert_array_equal(fingers(openpi_style, 0.0), fingers(openpi_style, 1.0))
    np.testing.assert_array_equal(fingers(openpi_style, -0.1), fingers(openpi_style, -1.0))


def test_clip_leaves_robosuite_holding_on_a_zero_command() -> None:
    """robosuite's Panda gripper moves by the command's sign: the two ways differ at exactly 0 only."""
    env = LiberoEnv.from_scene(spatial())
    try:
        held, closed, weak = fingers(env, 0.0), fingers(env, 1.0), fingers(env, 0.1)
    finally:
        env.close()
    assert held[0] > closed[0]  # 0 holds the fingers open, 1 closes them
    np.testing.assert_array_equal(weak, closed)


def test_step_limit_truncates_at_the_protocols_length(openpi_style: LiberoEnv) -> None:
    assert openpi_style.step_limit == 220
    openpi_style.reset(1)
    hold = np.array([0, 0, 0, 0, 0, 0, -1.0])
    truncated = [openpi_style.step(hold).truncated for _ in range(220)]
    assert truncated == [False] * 219 + [True]
    openpi_style.reset(2)  # a new episode counts from zero
    assert not openpi_style.step(hold).truncated


def test_a_scene_shorter_than_the_step_limit_is_refused_before_building() -> None:
    scene = spatial(step_limit="lerobot").model_copy(update={"max_steps": 220})
    with pytest.raises(ROSConfigError, match="max_steps 220") as refused:
        LiberoEnv.from_scene(scene)
    assert refused.value.field == "max_steps"


def test_a_step_limit_needs_a_suite() -> None:
    scene = SimEnvironment.model_validate(
        {
            "name": "custom",
            "env": "libero",
            "env_kwargs": {"bddl": str(ROOT / "scenes" / "sim" / "franka_libero_pnp.bddl"), "step_limit": "openpi"},
            "task": "pick up the milk and place it in the basket",
            "max_steps": 300,
        }
    )
    with pytest.raises(ROSConfigError, match="problem file") as refused:
        LiberoEnv.from_scene(scene)
    assert refused.value.field == "env_kwargs.step_limit"
