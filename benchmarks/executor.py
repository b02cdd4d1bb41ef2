"""Chunk executor benchmark: its cost on the tick thread, and what inference on the worker does to the tick.

1. ``ChunkedExecutor.step`` alone: back to back (its own work; target p50 <= 10 µs), then at 100 Hz
   for ``--seconds`` with a policy that takes 60 ms on the worker (what a tick pays, cold caches
   after each sleep included).
2. The hardware runner (null HAL with the SO-101 joints, null safety) at 30 Hz for ``--seconds``,
   twice: with the hold skill (no inference), then with a chunking skill whose inference is ~120 ms
   of ONNX Runtime work on the executor's worker (one intra-op thread; the GIL is released while
   it runs): tick p50/p99 and missed slots, and the ratio of the p99s (target: within 10 %).

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
from openral_rskill.chunks import ChunkRequest
from openral_rskill.executor import ChunkedExecutor
from openral_rskill.noop import HoldSkill
from openral_runner.hardware import HardwareRunner
from openral_world_state import WorldStateAggregator

CHUNK = 30


def _busy_model(layers: int) -> bytes:
    """An ONNX graph of ``layers`` 256x1024 @ 1024x1024 products: a policy's worth of work."""
    from onnx import TensorProto, helper, numpy_helper  # noqa: PLC0415

    rng = np.random.default_rng(0)
    weight = (rng.standard_normal((1024, 1024)) / 32).astype(np.float32)
    nodes, name = [], "x"
    for i in range(layers):
        nodes.append(helper.make_node("MatMul", [name, "w"], [f"m{i}"]))
        nodes.append(helper.make_node("Tanh", [f"m{i}"], [f"h{i}"]))
        name = f"h{i}"
    nodes.append(helper.make_node("ReduceMean", [name], ["y"], keepdims=0))
    graph = helper.make_graph(
        nodes,
        "busy",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [256, 1024])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [])],
        [numpy_helper.from_array(weight, "w")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return bytes(model.SerializeToString())


class BusyChunkSkill(RSkillBase):
    """Holds the pose in 30-row chunks, each after ~``work_ms`` of ONNX Runtime inference (one intra-op thread)."""

    def __init__(self, robot: RobotManifest, work_ms: float) -> None:
        super().__init__()
        import onnxruntime as ort  # noqa: PLC0415

        self.robot = robot
        self._info = RSkillInfo(skill_id="busy_chunk", chunk_size=CHUNK)
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        self._x = np.random.default_rng(1).standard_normal((256, 1024)).astype(np.float32)
        probe = ort.InferenceSession(_busy_model(1), options, providers=["CPUExecutionProvider"])
        probe.run(None, {"x": self._x})
        started = time.perf_counter()
        probe.run(None, {"x": self._x})
        layers = max(1, round(work_ms / 1e3 / (time.perf_counter() - started)))
        self._session = ort.InferenceSession(_busy_model(layers), options, providers=["CPUExecutionProvider"])
        started = time.perf_counter()
        self._session.run(None, {"x": self._x})
        self.inference_ms = (time.perf_counter() - started) * 1e3

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> BusyChunkSkill:
        return cls(robot, 120.0)

    @property
    def info(self) -> RSkillInfo:
        return self._info

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        self._session.run(None, {"x": self._x})  # the GIL is released for the whole inference
        joints = request.world.joint_state
        assert joints is not None
        return np.repeat(np.asarray(joints.positions, dtype=np.float64)[None, :], CHUNK, axis=0)

    def _step_impl(self, world_state: WorldState) -> Action:
        row = self._chunk_impl(ChunkRequest(world_state))[0]
        return Action(joint_names=self.robot.joint_names, targets=[row.tolist()])


def _step_cost(seconds: float) -> None:
    """Time ``step`` warm (back to back, the executor's own work) and after a 10 ms sleep (what a tick pays)."""
    names = [f"j{i}" for i in range(6)]
    world = WorldState(stamp_ns=0, joint_state=JointState(names=names, positions=[0.0] * 6))
    warm = ChunkedExecutor(lambda _w: np.zeros((1000, 6)), action_names=names, virtual_delay=lambda _i: 0)
    costs = []
    for tick in range(5000):
        t0 = time.perf_counter_ns()
        warm.step(tick, world)
        costs.append(time.perf_counter_ns() - t0)
    data = np.asarray(costs[100:]) / 1e3
    print(
        f"executor.step, warm: p50 {np.percentile(data, 50):.1f} µs, p99 {np.percentile(data, 99):.1f} µs "
        f"(target p50 <= 10 µs)"
    )

    def infer(_request: ChunkRequest) -> np.ndarray:
        time.sleep(0.06)
        return np.zeros((CHUNK, 6))

    executor = ChunkedExecutor(infer, action_names=names)
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
        f"executor.step at 100 Hz, first thing after each sleep: p50 {np.percentile(data, 50):.1f} µs, "
        f"p99 {np.percentile(data, 99):.1f} µs (cold caches after the wake-up: see wake_penalty.py); "
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
        # The example deployments' settings: the tick thread preempts the inference worker.
        realtime=RealtimeConfig(switch_interval_s=0.001, sched_fifo_priority=50),
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
    print(f"chunking skill: {busy.inference_ms:.0f} ms per inference (ONNX Runtime, 1 intra-op thread)")
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
