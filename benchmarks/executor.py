"""Chunk executor benchmark: its cost on the tick thread, and what inference on the worker does to the tick.

1. ``ChunkedExecutor.step`` alone, at 100 Hz for ``--seconds``, with a policy that takes 60 ms on
   the worker and returns 30-row chunks: p50/p99 of the time ``step`` takes (target p50 <= 10 µs).
2. The hardware runner (null HAL with the SO-101 joints, null safety) at 30 Hz for ``--seconds``,
   twice: with the hold skill (no inference), then with a chunking skill whose inference is ~120 ms
   of numpy work on the executor's worker (as an ONNX or torch policy's would be): tick p50/p99 and
   missed slots, and the ratio of the p99s (target: within 10 %).

Run:  uv run python benchmarks/executor.py [--seconds 20]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from _common import machine_line
from openral_core import Action, JointState, RealtimeConfig, RobotManifest, RSkillInfo, RunResult, WorldState
from openral_hal.manifests import load_robot_manifest
from openral_hal.null import NullHAL
from openral_rskill.base import RSkillBase
from openral_rskill.executor import ChunkedExecutor
from openral_rskill.noop import HoldSkill
from openral_runner.hardware import HardwareRunner
from openral_world_state import WorldStateAggregator

CHUNK = 30


class BusyChunkSkill(RSkillBase):
    """Holds the pose in 30-row chunks, each after ~``work_ms`` of numpy matrix work (GIL released inside BLAS)."""

    def __init__(self, robot: RobotManifest, work_ms: float) -> None:
        super().__init__()
        self.robot = robot
        self._info = RSkillInfo(skill_id="busy_chunk", chunk_size=CHUNK)
        self._a = np.random.default_rng(0).standard_normal((256, 256))
        started = time.perf_counter()
        self._a @ self._a
        one = time.perf_counter() - started
        self._repeats = max(1, int(work_ms / 1e3 / max(one, 1e-6)))

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> BusyChunkSkill:
        return cls(robot, 120.0)

    @property
    def info(self) -> RSkillInfo:
        return self._info

    def _step_impl(self, world_state: WorldState) -> Action:
        product = self._a
        for _ in range(self._repeats):
            product = np.tanh(product @ self._a / 256.0)
        assert world_state.joint_state is not None
        pose = list(world_state.joint_state.positions)
        return Action(joint_names=self.robot.joint_names, targets=[pose] * CHUNK)


def _step_cost(seconds: float) -> None:
    def infer(world: WorldState) -> np.ndarray:
        time.sleep(0.06)
        return np.zeros((CHUNK, 6))

    names = [f"j{i}" for i in range(6)]
    executor = ChunkedExecutor(infer, action_names=names, chunk_size=CHUNK)
    world = WorldState(stamp_ns=0, joint_state=JointState(names=names, positions=[0.0] * 6))
    costs = []
    period = 0.01
    start = time.perf_counter()
    tick = 0
    try:
        while time.perf_counter() - start < seconds:
            time.sleep(max(0.0, start + tick * period - time.perf_counter()))
            t0 = time.perf_counter_ns()
            executor.step(tick, world)
            costs.append(time.perf_counter_ns() - t0)
            tick += 1
    finally:
        executor.close()
    data = np.asarray(costs[10:]) / 1e3
    print(
        f"executor.step: {len(data)} ticks at 100 Hz, p50 {np.percentile(data, 50):.1f} µs, "
        f"p99 {np.percentile(data, 99):.1f} µs, max {data.max():.1f} µs (target p50 <= 10 µs); "
        f"{executor.stats.chunks_used} chunks used, {executor.stats.starved_ticks} starved ticks"
    )


def _run(skill: RSkillBase, robot: RobotManifest, seconds: float) -> RunResult:
    runner = HardwareRunner(
        hal=NullHAL(robot, {}),
        skill=skill,
        aggregator=WorldStateAggregator(joint_max_age_ms=1000.0),
        rate_hz=30.0,
        thumbnail_hz=0.0,
        action_names=robot.joint_names,
        realtime=RealtimeConfig(switch_interval_s=0.001),
    )
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        return runner.run(duration_s=seconds)
    finally:
        runner.deactivate()
        skill.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    print(machine_line())
    _step_cost(args.seconds)
    robot = load_robot_manifest("so101_follower")
    without = _run(HoldSkill(robot), robot, args.seconds)
    busy = BusyChunkSkill(robot, 120.0)
    with_inference = _run(busy, robot, args.seconds)
    for label, result in (("no inference", without), ("inference on worker", with_inference)):
        print(
            f"{label:<20} ticks {result.n_ticks:5d}  tick p50 {result.tick_ms_p50 * 1e3:7.1f} µs  "
            f"p99 {result.tick_ms_p99 * 1e3:8.1f} µs  missed slots {result.missed_slots}"
        )
    executor = with_inference.metadata.get("executor", {})
    print(f"executor: {executor}")
    print(f"tick p99 with / without inference: {with_inference.tick_ms_p99 / without.tick_ms_p99:.2f} (target <= 1.10)")


if __name__ == "__main__":
    main()
