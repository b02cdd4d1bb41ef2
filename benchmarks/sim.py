"""Simulation benchmark: what SimRunner adds to each env step, and episodes per second with 1 and 2 workers.

Two environments, each run the same episodes (same seeds) twice in one process:

* a bare loop: ``env.reset(seed)``, then ``action = policy(observation)``, ``env.step(action)``;
* ``SimRunner`` with the equivalent skill: world state per step, the skill's lifecycle, the
  action-box safety check, the tick span and metrics, episode bookkeeping.

``mock`` (a reaching task whose step costs microseconds) shows the runner's absolute cost per step;
``so101_pickplace`` (lerobot-env-so101 with its own ``PickPlaceController``) shows it against a
real MuJoCo step. Then the SO-101 pick scene's expert evaluation runs with 1 and 2 worker
processes and reports episodes per second, worker start-up included (``benchmarks/eval_scaling.py``
compares worker counts through ``openral benchmark run``, up to the CPU count).

Run:  uv run python benchmarks/sim.py [--episodes 10] [--worker-episodes 16]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from _common import machine_line
from openral_core import SimEnvironment
from openral_sim.build import run_episodes
from openral_sim.env import make_env
from openral_sim.evaluation import run_units, schedule_episodes

SCENES = Path(__file__).resolve().parents[1] / "scenes" / "sim"


def _bare(scene: SimEnvironment, policy: Callable[[Any], np.ndarray], reset: Callable[[], None]) -> tuple[int, float]:
    """Run the scene's episodes in a plain loop; returns (steps, seconds)."""
    env = make_env(scene)
    steps = 0
    elapsed = 0.0
    try:
        for episode in range(scene.n_episodes):
            observation = env.reset(scene.seed + episode)
            reset()
            started = time.perf_counter()
            for _ in range(scene.max_steps):
                step = env.step(policy(observation))
                observation = step.observation
                steps += 1
                if step.terminated or step.truncated or observation.info.get(scene.success_key):
                    break
            elapsed += time.perf_counter() - started
    finally:
        env.close()
    return steps, elapsed


def _runner(scene: SimEnvironment, skill: str) -> tuple[int, float]:
    batch = run_episodes(scene, skill)
    return sum(e.steps for e in batch.episodes), sum(batch.tick_ms) / 1e3


def _compare(
    name: str, scene: SimEnvironment, skill: str, policy: Callable[[Any], np.ndarray], reset: Callable[[], None]
) -> None:
    bare_steps, bare_s = _bare(scene, policy, reset)
    run_steps, run_s = _runner(scene, skill)
    bare_us = bare_s / bare_steps * 1e6
    run_us = run_s / run_steps * 1e6
    print(
        f"{name:18s} bare {bare_us:9.1f} µs/step ({bare_steps} steps)   SimRunner {run_us:9.1f} µs/step "
        f"({run_steps} steps)   added {run_us - bare_us:8.1f} µs/step = {100 * (run_us - bare_us) / bare_us:6.1f} %"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--worker-episodes", type=int, default=40)
    args = parser.parse_args()
    print(machine_line())

    mock = SimEnvironment.from_yaml(SCENES / "mock_reach.yaml").model_copy(
        update={"cameras": [], "n_episodes": args.episodes}
    )
    _compare(
        "mock",
        mock,
        "mock_reach_expert",
        lambda obs: np.clip((np.asarray(obs.privileged["target"]) - obs.state) * 20.0, -1.0, 1.0),
        lambda: None,
    )

    from lerobot_env_so101.scripted import PickPlaceController  # noqa: PLC0415

    controller = PickPlaceController(action_scale=0.025)
    pickplace = SimEnvironment.from_yaml(SCENES / "so101_pickplace.yaml").model_copy(
        update={"cameras": [], "n_episodes": args.episodes}
    )
    _compare(
        "so101_pickplace",
        pickplace,
        "so101_pickplace_expert",
        lambda obs: controller.act(
            obs.privileged["grasp_pos"], obs.privileged["block_pos"], obs.privileged["goal_pos"]
        ),
        controller.reset,
    )

    pick = SimEnvironment.from_yaml(SCENES / "so101_pick.yaml").model_copy(
        update={"cameras": [], "n_episodes": args.worker_episodes}
    )
    rates = {}
    for workers in (1, 2):
        units = schedule_episodes(pick, "so101_pick_expert", {}, pick.n_episodes, workers)
        started = time.perf_counter()
        batch = run_units(units, workers=workers)
        elapsed = time.perf_counter() - started
        rates[workers] = len(batch.episodes) / elapsed
        print(
            f"so101_pick expert, {workers} worker(s): {len(batch.episodes)} episodes in {elapsed:.1f} s = "
            f"{rates[workers]:.2f} episodes/s ({sum(e.success for e in batch.episodes)} succeeded)"
        )
    print(f"speed-up with 2 workers: {rates[2] / rates[1]:.2f}x")


if __name__ == "__main__":
    main()
