"""LeRobot checkpoints through ``lerobot_policy``: chunk latency cold and warm per device, and the first ticks.

ACT (a VGA camera and the joints, chunk 100, LeRobot's default sizes) and Diffusion (the same
inputs at 240x320, DDIM) are built with random weights, saved as ``lerobot-train`` saves them, and
loaded through the skill. Per device it prints the first inference without warm-up (what tick 1
would pay), then p50/p99 of warm inferences; then a 30 Hz ``HardwareRunner`` with the policy behind
the chunk executor, with and without warm-up: ticks until the first row reaches the robot, missed
slots, late ticks. Needs the 'lerobot' extra (Python 3.12)::

    UV_PROJECT_ENVIRONMENT=.venv-py312 uv run --python 3.12 --no-sync python benchmarks/lerobot_policy.py
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.factory import get_policy_class, make_pre_post_processors

from _common import machine_line
from openral_core import FrameEncoding, JointState, SensorFrame, SensorReaderConfig, WithheldReason, WorldState
from openral_hal.manifests import load_robot_manifest
from openral_hal.testing import RecordingHAL
from openral_rskill.chunks import ChunkRequest
from openral_rskill.lerobot_policy import LeRobotPolicySkill
from openral_runner.clock import SystemClock
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import ScriptedReader
from openral_world_state import WorldStateAggregator

SO101 = load_robot_manifest("so101_follower")


def _save(config: Any, folder: Path) -> Path:
    policy = get_policy_class(config.type)(config)
    stats: dict[str, dict[str, torch.Tensor]] = {}
    for key, feature in {**config.input_features, **config.output_features}.items():
        if feature.type is FeatureType.VISUAL:
            stats[key] = {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25)}
        else:
            stats[key] = {"mean": torch.zeros(feature.shape), "std": torch.ones(feature.shape)}
            stats[key] |= {"min": -torch.ones(feature.shape), "max": torch.ones(feature.shape)}
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(folder)
    pre.save_pretrained(folder)
    post.save_pretrained(folder)
    return folder


def _features(height: int, width: int) -> tuple[dict[str, PolicyFeature], dict[str, PolicyFeature]]:
    return (
        {
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(6,)),
            "observation.images.front": PolicyFeature(type=FeatureType.VISUAL, shape=(3, height, width)),
        },
        {"action": PolicyFeature(type=FeatureType.ACTION, shape=(6,))},
    )


def build(root: Path, diffusion_steps: int) -> dict[str, Path]:
    inputs, outputs = _features(480, 640)
    act = ACTConfig(
        input_features=inputs,
        output_features=outputs,
        chunk_size=100,
        n_action_steps=100,
        device="cpu",
        pretrained_backbone_weights=None,
    )
    inputs, outputs = _features(240, 320)
    diffusion = DiffusionConfig(
        input_features=inputs,
        output_features=outputs,
        crop_shape=None,
        noise_scheduler_type="DDIM",
        num_inference_steps=diffusion_steps,
        device="cpu",
        pretrained_backbone_weights=None,
    )
    return {"act": _save(act, root / "act"), "diffusion": _save(diffusion, root / "diffusion")}


def world(height: int, width: int, stamp: int = 1) -> WorldState:
    pixels = np.random.default_rng(stamp).integers(0, 256, (height, width, 3), dtype=np.uint8)
    frame = SensorFrame(
        sensor_id="front", stamp_ns=stamp, width=width, height=height, encoding=FrameEncoding.BGR8, data=pixels
    )
    return WorldState(
        stamp_ns=stamp,
        joint_state=JointState(names=SO101.joint_names, positions=[0.0] * 6, stamp_ns=stamp),
        image_frames={"front": frame},
        task="pick the cube",
    )


def skill(path: Path, device: str, warmup: int) -> LeRobotPolicySkill:
    built = LeRobotPolicySkill.from_config(
        {"path": str(path), "device": device, "warmup_inferences": warmup}, robot=SO101, rate_hz=30
    )
    built.configure()
    built.activate()
    return built


def latency(path: Path, device: str, calls: int) -> None:
    observation = ChunkRequest(world(480, 640))
    cold = skill(path, device, warmup=0)
    start = time.perf_counter()
    cold.step_chunk(observation)
    first_ms = (time.perf_counter() - start) * 1e3
    cold.shutdown()
    warm = skill(path, device, warmup=3)
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        warm.step_chunk(observation)
        times.append((time.perf_counter() - start) * 1e3)
    warm.shutdown()
    times.sort()
    p99 = times[min(len(times) - 1, round(0.99 * (len(times) - 1)))]
    print(
        f"  {path.name:9s} {device:4s}  first call without warm-up {first_ms:8.1f} ms   "
        f"warm p50 {statistics.median(times):7.1f} ms  p99 {p99:7.1f} ms  ({calls} calls)"
    )


def first_ticks(path: Path, device: str, warmup: int, ticks: int) -> None:
    built = skill(path, device, warmup)
    clock = SystemClock()
    runner = HardwareRunner(
        hal=RecordingHAL(SO101, clock_ns=clock.now_ns),
        skill=built,
        aggregator=WorldStateAggregator(sensors=[SensorReaderConfig(sensor_id="front")], clock=clock.now_ns),
        sensor_readers=[ScriptedReader("front", clock, width=640, height=480)],  # type: ignore[arg-type]
        rate_hz=30.0,
        clock=clock,
        thumbnail_hz=0.0,
        action_names=SO101.joint_names,
        task="pick the cube",
    )
    runner.activate()
    try:
        result = runner.run(ticks)
        awaiting = sum(t.withheld_reason is WithheldReason.AWAITING_CHUNK for t in runner.recent_ticks)
    finally:
        runner.deactivate()
        built.shutdown()
    print(
        f"  {path.name:9s} {device:4s} warm-up {warmup}: {awaiting:3d} ticks before the first row, "
        f"missed slots {result.missed_slots}, deadline misses {result.deadline_misses}, "
        f"tick p99 {result.tick_ms_p99:.2f} ms"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--devices", nargs="*", default=None, help="default: cpu, and cuda when there is one")
    parser.add_argument("--calls", type=int, default=20, help="warm inferences timed per policy and device")
    parser.add_argument("--diffusion-steps", type=int, default=10)
    parser.add_argument("--ticks", type=int, default=90)
    args = parser.parse_args()
    devices = args.devices or ["cpu", *(["cuda"] if torch.cuda.is_available() else [])]
    print(machine_line())
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, cuda {torch.cuda.is_available()}")
    if torch.cuda.is_available():
        print(f"gpu: {torch.cuda.get_device_name(0)}")
    with tempfile.TemporaryDirectory() as scratch:
        paths = build(Path(scratch), args.diffusion_steps)
        print("chunk latency (skill.step_chunk: mapping, preprocessor, model, postprocessor)")
        for device in devices:
            for name, path in paths.items():
                latency(path, device, args.calls if name == "act" or device != "cpu" else max(3, args.calls // 4))
        print(f"first ticks at 30 Hz behind the chunk executor ({args.ticks} ticks, ACT)")
        for device in devices:
            for warmup in (0, 3):
                first_ticks(paths["act"], device, warmup, args.ticks)


if __name__ == "__main__":
    main()
