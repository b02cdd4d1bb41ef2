"""Perception benchmark: what event detectors beside the policy cost the tick, and what they cost themselves.

1. The twin deployment with its camera (``deployments/so101_twin_perception.yaml``) for
   ``--seconds``, twice in one run: the perception observer off, then on (motion, scene change and
   the ONNX cube detector at 5 Hz per kind, events published on Zenoh). Tick-start jitter p50/p99
   and tick p99; target: p99 jitter with detectors on within 1.5x of off.
2. Each detector's own time per frame at 320x240 (what the worker spends, off the tick).

Run:  uv run python benchmarks/perception.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from _common import machine_line, run_deployment
from openral_core import RobotEnvironment
from openral_perception.detectors.motion import MotionDetector
from openral_perception.detectors.objects import ObjectsDetector
from openral_perception.detectors.scene_change import SceneChangeDetector
from openral_perception.frame import DetectorFrame
from openral_perception.observer import PerceptionObserver

ROOT = Path(__file__).resolve().parents[1]
DEPLOYMENTS = ROOT / "deployments"


def twin_jitter(seconds: float, *, perception: bool) -> tuple[float, float, float, dict[str, Any]]:
    env = RobotEnvironment.from_yaml(DEPLOYMENTS / "so101_twin_perception.yaml")
    if perception:
        observers = [
            o.model_copy(update={"params": {**o.params, "zenoh": {"listen": ["tcp/127.0.0.1:0"]}}})
            for o in env.observers
        ]
    else:
        observers = []
    env = env.model_copy(update={"observers": observers})
    result, runner = run_deployment(env, DEPLOYMENTS, seconds)
    published: dict[str, Any] = {}
    for observer in runner.observers:
        if isinstance(observer, PerceptionObserver):
            published = {
                "events": dict(observer.publisher.published),
                "dropped": sum(observer.publisher.dropped.values()),
            }
    return result.start_jitter_us_p50, result.start_jitter_us_p99, result.tick_ms_p99, published


def detector_costs(repeats: int = 50) -> list[tuple[str, float]]:
    """Each detector's time per frame, on fresh views (so each pays for its grey or colour form as the first would)."""
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (240, 320, 3), dtype=np.uint8) for _ in range(2)]
    detectors = [
        ("motion", MotionDetector()),
        ("scene_change", SceneChangeDetector()),
        (
            "objects (cube_detector.onnx)",
            ObjectsDetector(str(ROOT / "models" / "cube_detector.onnx"), labels=["cube"], model_id="cube"),
        ),
    ]
    costs = []
    for name, detector in detectors:
        detector.detect(DetectorFrame.from_array(frames[0], sensor_id="bench"))
        started = time.perf_counter()
        for i in range(repeats):
            detector.detect(DetectorFrame.from_array(frames[i % 2], sensor_id="bench"))
        costs.append((name, (time.perf_counter() - started) / repeats * 1e3))
    return costs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    print(machine_line())
    off = twin_jitter(args.seconds, perception=False)
    on = twin_jitter(args.seconds, perception=True)
    print(f"twin + camera, detectors off: jitter p50 {off[0]:.1f} µs p99 {off[1]:.1f} µs, tick p99 {off[2]:.2f} ms")
    print(f"twin + camera, detectors on:  jitter p50 {on[0]:.1f} µs p99 {on[1]:.1f} µs, tick p99 {on[2]:.2f} ms")
    print(f"  events {on[3].get('events')}, frames not looked at {on[3].get('dropped')}")
    print(f"on / off p99 jitter ratio: {on[1] / max(off[1], 1e-9):.2f}x (target <= 1.5x)")
    for name, ms in detector_costs():
        print(f"detector {name:30s} {ms:7.2f} ms per 320x240 frame (on the worker)")


if __name__ == "__main__":
    main()
