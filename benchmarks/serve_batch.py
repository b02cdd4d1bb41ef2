"""One policy server, N robots: batch 1 against dynamic batching, in inferences per second and client round trips.

N client processes (``RemotePolicyClient``, what the ``remote_policy`` skill uses) each ask one
``openral serve`` for a chunk at ``--rate-hz`` for ``--seconds``, all starting together. The server
runs once with ``--max-batch 1`` (one request per inference) and once with ``--max-batch B
--max-wait-ms W`` (concurrent robots' requests in one inference). Per N it prints the chunks
served per second, the clients' round trip p50/p99 and the failed requests (late, superseded,
refused), then the batched/unbatched throughput ratio and p99 ratio against one client.

Policies:

* ``act``: LeRobot's ACT with random weights, a VGA camera and the joints, chunk 100 (the
  configuration of ``benchmarks/lerobot_policy.py``); needs the 'lerobot' extra (Python 3.12)
  and is what the GPU figures are for (``--device cuda``).
* ``onnx``: an MLP chunk policy in ONNX with a dynamic batch dimension (joints in, 50x6 out,
  50 M parameters), ONNX Runtime on the CPU; runs in the default environment.

Run::

    uv run python benchmarks/serve_batch.py --policy onnx --clients 1,4,16,64
    UV_PROJECT_ENVIRONMENT=.venv-py312 uv run --python 3.12 --no-sync \\
        python benchmarks/serve_batch.py --policy act --device cuda --clients 1,4,16,32,64
"""

from __future__ import annotations

import argparse
import itertools
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from _common import machine_line
from openral_core import FrameEncoding, JointState, SensorFrame, WorldState
from openral_hal.manifests import load_robot_manifest
from openral_remote.testing import free_endpoint

SO101 = load_robot_manifest("so101_follower")
POLICY_NAME = "bench"


def onnx_model(folder: Path, *, hidden: int, layers: int = 4, chunk: int = 50) -> Path:
    """An MLP from the joints to a ``(batch, chunk, 6)`` chunk, random weights, batch dimension dynamic.

    Wide enough that one inference reads its weights from memory rather than cache, as a large
    model on a GPU does: batch 1 is bound by memory, not arithmetic, which is what batching pays off.
    """
    from onnx import TensorProto, helper, numpy_helper  # noqa: PLC0415

    rng = np.random.default_rng(0)
    sizes = [6] + [hidden] * (layers - 1) + [chunk * 6]
    nodes, weights = [], []
    name = "observation"
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        weights += [
            numpy_helper.from_array((rng.standard_normal((n_in, n_out)) / np.sqrt(n_in)).astype(np.float32), f"w{i}"),
            numpy_helper.from_array(np.zeros(n_out, dtype=np.float32), f"b{i}"),
        ]
        nodes.append(helper.make_node("Gemm", [name, f"w{i}", f"b{i}"], [f"z{i}"]))
        name = f"z{i}"
        if i < len(sizes) - 2:
            nodes.append(helper.make_node("Tanh", [name], [f"h{i}"]))
            name = f"h{i}"
    weights.append(numpy_helper.from_array(np.array([-1, chunk, 6], dtype=np.int64), "shape"))
    nodes.append(helper.make_node("Reshape", [name, "shape"], ["actions"]))
    graph = helper.make_graph(
        nodes,
        "bench_mlp",
        [helper.make_tensor_value_info("observation", TensorProto.FLOAT, ["batch", 6])],
        [helper.make_tensor_value_info("actions", TensorProto.FLOAT, ["batch", chunk, 6])],
        weights,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {"chunk_size": str(chunk), "openral.observation": '["joint_state"]'})
    path = folder / "bench_mlp.onnx"
    path.write_bytes(model.SerializeToString())
    return path


def skill_and_params(policy: str, folder: Path, device: str, hidden: int) -> tuple[str, dict[str, Any]]:
    if policy == "onnx":
        return "onnx_policy", {"model": str(onnx_model(folder, hidden=hidden)), "intra_op_threads": 0}
    from lerobot_policy import build  # noqa: PLC0415 (the 'lerobot' extra: Python 3.12)

    return "lerobot_policy", {"path": str(build(folder, 10)["act"]), "device": device, "warmup_inferences": 3}


def observation(policy: str, seed: int) -> WorldState:
    rng = np.random.default_rng(seed)
    joints = JointState(names=SO101.joint_names, positions=rng.uniform(-0.5, 0.5, 6).tolist(), stamp_ns=1)
    if policy == "onnx":
        return WorldState(stamp_ns=1, joint_state=joints)
    pixels = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    frame = SensorFrame(sensor_id="front", stamp_ns=1, width=640, height=480, encoding=FrameEncoding.BGR8, data=pixels)
    return WorldState(stamp_ns=1, joint_state=joints, image_frames={"front": frame}, task="pick the cube")


def client(plan: tuple[str, str, int, float, float, float]) -> dict[str, Any]:
    """One robot: connect, then ask at ``rate_hz`` from ``start_at`` for ``seconds``."""
    endpoint, policy, seed, start_at, seconds, rate_hz = plan
    from openral_remote.client import RemotePolicyClient  # noqa: PLC0415
    from openral_remote.config import ZenohConfig  # noqa: PLC0415
    from openral_remote.keys import PolicyKeys  # noqa: PLC0415

    remote = RemotePolicyClient(
        PolicyKeys.of(SO101.robot_id, POLICY_NAME), ZenohConfig(connect=[endpoint]), deadline_ms=5000
    )
    remote.connect(timeout_s=120)
    world = observation(policy, seed)
    for _ in range(600):  # this client's first chunk is not measured (an overloaded host may miss a lease)
        try:
            remote.infer(world)
            break
        except Exception:
            time.sleep(0.1)
    round_trips: list[float] = []
    failures = 0
    time.sleep(max(0.0, start_at - time.time()))
    period = 1.0 / rate_hz
    begun = time.perf_counter()
    tick = 0
    while time.perf_counter() - begun < seconds:
        started = time.perf_counter()
        try:
            remote.infer(world)
            round_trips.append((time.perf_counter() - started) * 1e3)
        except Exception:
            failures += 1
        tick += 1
        time.sleep(max(0.0, begun + tick * period - time.perf_counter()))
    remote.close()
    return {"round_trips": round_trips, "failures": failures}


def run(
    endpoint: str, skill: str, params: dict[str, Any], *, n: int, args: argparse.Namespace, batch: int
) -> dict[str, Any]:
    command = [
        sys.executable,
        "-m",
        "openral_cli",
        "serve",
        "--skill",
        skill,
        "--skill-params",
        json.dumps(params),
        "--robot",
        SO101.robot_id,
        "--rate-hz",
        str(args.rate_hz),
        "--name",
        POLICY_NAME,
        "--listen",
        endpoint,
        "--max-batch",
        str(batch),
        "--max-wait-ms",
        str(args.max_wait_ms),
        "--max-clients",
        str(max(n, 1)),
    ]
    server = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        start_at = time.time() + 15.0 + 0.3 * n  # every client connected and warm by then
        with multiprocessing.get_context("spawn").Pool(n) as pool:
            results = pool.map(
                client, [(endpoint, args.policy, i, start_at, args.seconds, args.rate_hz) for i in range(n)]
            )
    finally:
        server.terminate()
        server.wait(timeout=30)
    round_trips = np.array([rt for r in results for rt in r["round_trips"]])
    return {
        "served_per_s": len(round_trips) / args.seconds,
        "asked_per_s": n * args.rate_hz,
        "p50_ms": float(np.percentile(round_trips, 50)) if len(round_trips) else float("nan"),
        "p99_ms": float(np.percentile(round_trips, 99)) if len(round_trips) else float("nan"),
        "failures": sum(r["failures"] for r in results),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", choices=["onnx", "act"], default="onnx")
    parser.add_argument("--device", default="cpu", help="act: cpu, cuda or auto")
    parser.add_argument("--clients", default="1,4,16,64", help="Client counts, comma-separated.")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rate-hz", type=float, default=10.0)
    parser.add_argument("--max-batch", type=int, default=64)
    parser.add_argument("--max-wait-ms", type=float, default=5.0)
    parser.add_argument("--hidden", type=int, default=4096, help="onnx: the MLP's width (4096: 50 M parameters).")
    args = parser.parse_args()
    counts = [int(n) for n in args.clients.split(",")]
    print(machine_line())
    print(f"policy {args.policy} on {args.device}; each client asks at {args.rate_hz:g} Hz for {args.seconds:g} s")
    with tempfile.TemporaryDirectory() as folder:
        skill, params = skill_and_params(args.policy, Path(folder), args.device, args.hidden)
        rows: list[tuple[int, dict[str, Any], dict[str, Any]]] = []
        print(f"{'N':>4} {'mode':>10} {'asked/s':>8} {'served/s':>9} {'p50 ms':>8} {'p99 ms':>8} {'failed':>7}")
        for n in counts:
            figures = {}
            for label, batch in (("batch 1", 1), (f"batch {args.max_batch}", args.max_batch)):
                result = run(free_endpoint(), skill, params, n=n, args=args, batch=batch)
                figures[label] = result
                print(
                    f"{n:>4} {label:>10} {result['asked_per_s']:>8.0f} {result['served_per_s']:>9.1f} "
                    f"{result['p50_ms']:>8.1f} {result['p99_ms']:>8.1f} {result['failures']:>7d}",
                    flush=True,
                )
            rows.append((n, figures["batch 1"], figures[f"batch {args.max_batch}"]))
    single_p99 = rows[0][1]["p99_ms"] if rows and rows[0][0] == 1 else float("nan")
    print("\nbatched vs batch 1:")
    for n, one, many in rows:
        print(
            f"  N={n:>3}: throughput x{many['served_per_s'] / max(one['served_per_s'], 1e-9):.2f}, "
            f"batched p99 = {many['p99_ms'] / single_p99:.2f}x the single-client p99"
        )
    print(f"(cpu count {os.cpu_count()})")


if __name__ == "__main__":
    main()
