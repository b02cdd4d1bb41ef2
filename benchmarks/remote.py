"""Remote inference benchmark: one VGA observation in, one 50x6 chunk out, at 30 Hz, five ways, one run.

1. openral over Zenoh TCP on loopback (``openral_remote``: the wire codec, a queryable, one worker,
   the observation rebuilt as a ``WorldState`` and stepped through a skill, the chunk encoded back).
2. The same over Zenoh shared memory (the request is written into a shared segment).
   Then TCP, TLS and mutual TLS (certificates of a private CA made for the run) side by side:
   three servers, the three clients asked in turn in every slot, so load drifts hit all three
   alike; TLS's cost against TCP is printed as ratios. Then the TCP round trip as the chunk
   executor asks for it: the ``remote_policy`` skill's chunk.
3. gRPC + pickle, as LeRobot's async inference does it: the observation dict pickled into a
   unary call, the chunk pickled back (code execution on both ends; here only for comparison).
4. Zenoh alone: the same bytes to a queryable whose worker replies a fixed chunk's bytes (no
   codec, no skill): the floor that openral's own Python work adds to. openral's share is its TCP
   p50 minus this one's, printed last.

Then: how long after a server's SIGKILL the client knows it is down (liveliness, no request made).

Each server runs in its own process and returns a fixed-shape chunk at once, so the figures are
the transport's and the codec's; paced at the rate (caches go cold between requests, as on a
robot) and back to back. Every process keeps its message memory (``keep_message_memory``), as
``openral serve`` and a deployment on a remote policy do. Target: openral TCP p50 <= 3 ms on
loopback at 30 Hz.

Run:  uv run python benchmarks/remote.py [--seconds 10] [--rate-hz 30]
"""

from __future__ import annotations

import argparse
import pickle
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent import futures
from pathlib import Path
from typing import Any

import numpy as np

from _common import machine_line
from openral_core import FrameEncoding, JointState, SensorFrame, WorldState
from openral_hal.manifests import load_robot_manifest
from openral_remote.allocator import keep_message_memory
from openral_remote.client import RemotePolicyClient
from openral_remote.codec import encode
from openral_remote.config import RemotePolicyParams, TlsConfig, ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.observation import world_fields
from openral_remote.skill import RemotePolicySkill
from openral_remote.testing import POLICY, ROBOT, free_endpoint
from openral_remote.testing_tls import make_ca, make_certificate
from openral_rskill.chunks import ChunkRequest

CHUNK, DIMS = 50, 6
GRPC_METHOD = "/openral.bench.Policy/Infer"


def _world() -> WorldState:
    image = np.random.default_rng(0).integers(0, 256, size=(480, 640, 3), dtype=np.uint8)
    frame = SensorFrame(sensor_id="front", stamp_ns=1, width=640, height=480, encoding=FrameEncoding.BGR8, data=image)
    joints = JointState(names=[f"j{i}" for i in range(DIMS)], positions=[0.1] * DIMS)
    return WorldState(stamp_ns=1, joint_state=joints, image_frames={"front": frame})


Timings = tuple[list[float], list[float]]
"""Round trips in ms: paced at the rate, then back to back."""


def _paced(call: Callable[[], Any], seconds: float, rate_hz: float) -> Timings:
    """Round trips (ms) of ``call`` on an absolute 1/rate schedule after a warm-up, then as many back to back."""
    for _ in range(20):
        call()
    period = 1.0 / rate_hz
    paced: list[float] = []
    start = time.perf_counter()
    count = int(seconds * rate_hz)
    for k in range(count):
        slot = start + k * period
        delay = slot - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        began = time.perf_counter()
        call()
        paced.append((time.perf_counter() - began) * 1e3)
    back_to_back: list[float] = []
    for _ in range(count):
        began = time.perf_counter()
        call()
        back_to_back.append((time.perf_counter() - began) * 1e3)
    return paced, back_to_back


def _policy_server(endpoint: str, rate_hz: float, *extra: str) -> subprocess.Popen[bytes]:
    """A policy server of a fixed-shape chunk (``openral_remote.testing``) in its own process."""
    return subprocess.Popen(
        [
            *(sys.executable, "-m", "openral_remote.testing", "--listen", endpoint, "--dims", str(DIMS)),
            *("--chunk-size", str(CHUNK), "--rate-hz", str(rate_hz), "--observation", "all", *extra),
        ],
    )


class Pki:
    """A private CA, the server's certificate and the robot's, in a temporary folder."""

    def __init__(self, folder: Path) -> None:
        self.ca = make_ca(folder)
        self.server = make_certificate(folder, "policy-server", self.ca)
        self.robot = make_certificate(folder, "robot-1", self.ca)

    def server_args(self, mutual: bool) -> list[str]:
        files = ["--tls-ca", str(self.ca.cert), "--tls-cert", str(self.server.cert), "--tls-key", str(self.server.key)]
        return [*files, "--mtls"] if mutual else files

    def robot_tls(self, mutual: bool) -> TlsConfig:
        if not mutual:
            return TlsConfig(ca=str(self.ca.cert))
        return TlsConfig(ca=str(self.ca.cert), cert=str(self.robot.cert), key=str(self.robot.key), mutual=True)


def _zenoh(seconds: float, rate_hz: float, shared_memory: bool) -> Timings:
    endpoint = free_endpoint()
    server = _policy_server(endpoint, rate_hz)
    client = RemotePolicyClient(
        PolicyKeys.of(ROBOT, POLICY), ZenohConfig(connect=[endpoint], shared_memory=shared_memory), deadline_ms=2000
    )
    try:
        client.connect(timeout_s=30)
        world = _world()
        rows = client.infer(world)
        assert rows.shape == (CHUNK, DIMS), rows.shape
        return _paced(lambda: client.infer(world), seconds, rate_hz)
    finally:
        client.close()
        server.terminate()
        server.wait(10)


SECURITY = {"TCP": None, "TLS": False, "mutual TLS": True}
"""The links compared side by side: plain, TLS (the robot checks the server), mutual TLS (both check)."""


def _secured(seconds: float, rate_hz: float, pki: Pki) -> dict[str, Timings]:
    """TCP, TLS and mutual TLS round trips, the three clients asked in turn in each slot (and back to back)."""
    servers: list[subprocess.Popen[bytes]] = []
    clients: dict[str, RemotePolicyClient] = {}
    try:
        for index, (name, mutual) in enumerate(SECURITY.items()):
            endpoint, zenoh_id = free_endpoint(), f"{index + 1}0"  # its own id: three servers of one key
            if mutual is None:
                servers.append(_policy_server(endpoint, rate_hz, "--zenoh-id", zenoh_id))
                zenoh = ZenohConfig(connect=[endpoint], shared_memory=False)
            else:
                endpoint = endpoint.replace("tcp/", "tls/", 1)
                servers.append(_policy_server(endpoint, rate_hz, "--zenoh-id", zenoh_id, *pki.server_args(mutual)))
                zenoh = ZenohConfig(connect=[endpoint], shared_memory=False, tls=pki.robot_tls(mutual))
            clients[name] = RemotePolicyClient(PolicyKeys.of(ROBOT, POLICY), zenoh, deadline_ms=2000)
            clients[name].connect(timeout_s=30)
        world = _world()
        for client in clients.values():
            assert client.infer(world).shape == (CHUNK, DIMS)
            for _ in range(20):
                client.infer(world)
        period = 1.0 / rate_hz
        count = int(seconds * rate_hz)
        paced: dict[str, list[float]] = {name: [] for name in clients}
        back_to_back: dict[str, list[float]] = {name: [] for name in clients}
        start = time.perf_counter()
        for k in range(count):
            delay = start + k * period - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            for name, client in clients.items():
                began = time.perf_counter()
                client.infer(world)
                paced[name].append((time.perf_counter() - began) * 1e3)
        for _ in range(count):
            for name, client in clients.items():
                began = time.perf_counter()
                client.infer(world)
                back_to_back[name].append((time.perf_counter() - began) * 1e3)
        return {name: (paced[name], back_to_back[name]) for name in clients}
    finally:
        for client in clients.values():
            client.close()
        for server in servers:
            server.terminate()
            server.wait(10)


def _skill(seconds: float, rate_hz: float) -> Timings:
    """The round trip as the chunk executor sees it: ``remote_policy``'s ``step_chunk`` (client, skill, TCP)."""
    endpoint = free_endpoint()
    server = _policy_server(endpoint, rate_hz)
    params = RemotePolicyParams(
        policy=POLICY,
        robot=ROBOT,
        zenoh=ZenohConfig(connect=[endpoint], shared_memory=False),
        deadline_ms=2000,
        connect_timeout_s=30,
    )
    try:
        skill = RemotePolicySkill(load_robot_manifest("so101_follower"), params, rate_hz=rate_hz)
        skill.configure()
        skill.activate()
        try:
            request = ChunkRequest(_world())
            rows = skill.step_chunk(request)
            assert rows.shape == (CHUNK, DIMS), rows.shape
            return _paced(lambda: skill.step_chunk(request), seconds, rate_hz)
        finally:
            skill.shutdown()
    finally:
        server.terminate()
        server.wait(10)


def grpc_server(port: int) -> None:
    """LeRobot's way: pickled observation in, pickled chunk out (never expose this to a network)."""
    import grpc  # noqa: PLC0415

    chunk = np.zeros((CHUNK, DIMS), dtype=np.float32)

    def infer(observation: dict[str, Any], _context: Any) -> np.ndarray:
        assert observation["observation.images.front"].shape == (480, 640, 3)
        return chunk

    handler = grpc.method_handlers_generic_handler(
        "openral.bench.Policy",
        {"Infer": grpc.unary_unary_rpc_method_handler(infer, pickle.loads, pickle.dumps)},
    )
    options = [("grpc.max_receive_message_length", 8 << 20), ("grpc.max_send_message_length", 8 << 20)]
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=1), options=options)
    server.add_generic_rpc_handlers((handler,))
    server.add_insecure_port(f"127.0.0.1:{port}")
    server.start()
    server.wait_for_termination()


def _grpc(seconds: float, rate_hz: float) -> Timings:
    import grpc  # noqa: PLC0415

    port = int(free_endpoint().rsplit(":", 1)[1])
    server = subprocess.Popen([sys.executable, __file__, "--grpc-server", str(port)])
    options = [("grpc.max_receive_message_length", 8 << 20), ("grpc.max_send_message_length", 8 << 20)]
    channel = grpc.insecure_channel(f"127.0.0.1:{port}", options=options)
    try:
        grpc.channel_ready_future(channel).result(timeout=30)
        infer = channel.unary_unary(GRPC_METHOD, request_serializer=pickle.dumps, response_deserializer=pickle.loads)
        world = _world()
        frame = (world.image_frames or {})["front"]

        def call() -> None:
            joints = world.joint_state
            assert joints is not None
            observation = {
                "observation.images.front": frame.as_array(),
                "observation.state": np.asarray(joints.positions, dtype=np.float32),
                "timestamp": time.time(),
            }
            rows = infer(observation, timeout=2.0)
            assert rows.shape == (CHUNK, DIMS)

        return _paced(call, seconds, rate_hz)
    finally:
        channel.close()
        server.terminate()
        server.wait(10)


ECHO_KEY = "openral/bench/echo"


def echo_server(endpoint: str) -> None:
    """Zenoh alone: a queryable whose worker thread answers every request with a fixed chunk's bytes."""
    import collections  # noqa: PLC0415
    import threading  # noqa: PLC0415

    from openral_remote.session import open_session  # noqa: PLC0415

    reply = np.zeros((CHUNK, DIMS), dtype=np.float64).tobytes()
    jobs: collections.deque[Any] = collections.deque()
    wake = threading.Condition()

    def work() -> None:
        while True:
            with wake:
                while not jobs:
                    wake.wait()
                query = jobs.popleft()
            query.reply(ECHO_KEY, reply)
            query.drop()

    def on_query(query: Any) -> None:
        query.payload.to_bytes()  # what any server does with the request: take it out of Zenoh
        with wake:
            jobs.append(query)
            wake.notify()

    keep_message_memory()
    session = open_session(ZenohConfig(listen=[endpoint]))
    threading.Thread(target=work, daemon=True).start()
    session.declare_queryable(ECHO_KEY, on_query, complete=True)
    threading.Event().wait()


def _echo(seconds: float, rate_hz: float) -> Timings:
    from openral_remote.session import open_session  # noqa: PLC0415

    endpoint = free_endpoint()
    server = subprocess.Popen([sys.executable, __file__, "--echo-server", endpoint])
    session = open_session(ZenohConfig(connect=[endpoint], shared_memory=False))
    try:
        message = encode(world_fields(_world())[0])
        querier = session.declare_querier(ECHO_KEY, timeout=2.0)

        def call() -> None:
            for reply in querier.get(payload=message):
                assert reply.ok is not None
                return
            raise RuntimeError("no reply yet")

        deadline = time.monotonic() + 30
        while True:
            try:
                call()
                break
            except RuntimeError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        return _paced(call, seconds, rate_hz)
    finally:
        session.close()
        server.terminate()
        server.wait(10)


def _kill_detection(repeats: int) -> list[float]:
    """Milliseconds from a server's SIGKILL to ``available()`` turning false, without a request."""
    import os  # noqa: PLC0415
    import signal  # noqa: PLC0415

    found: list[float] = []
    for _ in range(repeats):
        endpoint = free_endpoint()
        server = subprocess.Popen([sys.executable, "-m", "openral_remote.testing", "--listen", endpoint])
        client = RemotePolicyClient(PolicyKeys.of(ROBOT, POLICY), ZenohConfig(connect=[endpoint]))
        try:
            client.connect(timeout_s=30)
            killed = time.perf_counter()
            os.kill(server.pid, signal.SIGKILL)
            while client.available() and time.perf_counter() - killed < 5:
                time.sleep(0.0002)
            found.append((time.perf_counter() - killed) * 1e3)
        finally:
            client.close()
            server.wait(10)
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rate-hz", type=float, default=30.0)
    parser.add_argument("--grpc-server", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--echo-server", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.grpc_server is not None:
        grpc_server(args.grpc_server)
        return
    if args.echo_server is not None:
        echo_server(args.echo_server)
        return
    keep_message_memory()
    print(machine_line())
    print(f"VGA BGR observation (921,600 B of pixels) + {DIMS} joints in, {CHUNK}x{DIMS} chunk out")
    print(f"paced at {args.rate_hz:g} Hz for {args.seconds:g} s, then as many back to back")
    with tempfile.TemporaryDirectory(prefix="openral-bench-pki-") as folder:
        secured = _secured(args.seconds, args.rate_hz, Pki(Path(folder)))
    rows = [
        ("openral / Zenoh TCP", _zenoh(args.seconds, args.rate_hz, shared_memory=False)),
        ("openral / Zenoh shared memory", _zenoh(args.seconds, args.rate_hz, shared_memory=True)),
        ("openral / Zenoh TCP, beside TLS", secured["TCP"]),
        ("openral / Zenoh TLS", secured["TLS"]),
        ("openral / Zenoh mutual TLS", secured["mutual TLS"]),
        ("openral / remote_policy, TCP", _skill(args.seconds, args.rate_hz)),
        ("gRPC + pickle (LeRobot's way)", _grpc(args.seconds, args.rate_hz)),
        ("Zenoh alone, TCP (bytes echo)", _echo(args.seconds, args.rate_hz)),
    ]
    detection = _kill_detection(5)
    tcp_p50 = float(np.percentile(rows[0][1][0], 50))
    print(
        f"{'transport':32s} {'n':>5s} {'p50 ms':>8s} {'p99 ms':>8s} {'max ms':>8s} "
        f"{'p50 / openral TCP':>18s} {'back-to-back p50':>17s}"
    )
    for name, (paced, back_to_back) in rows:
        p50, p99 = np.percentile(paced, [50, 99])
        b2b = float(np.percentile(back_to_back, 50))
        print(f"{name:32s} {len(paced):5d} {p50:8.2f} {p99:8.2f} {max(paced):8.2f} {p50 / tcp_p50:18.2f} {b2b:17.2f}")

    tcp_paced, tcp_b2b = secured["TCP"]
    for name in ("TLS", "mutual TLS"):
        paced, back_to_back = secured[name]
        for mode, mine, theirs in (("paced", paced, tcp_paced), ("back to back", back_to_back, tcp_b2b)):
            p50, base = float(np.percentile(mine, 50)), float(np.percentile(theirs, 50))
            p99, base99 = float(np.percentile(mine, 99)), float(np.percentile(theirs, 99))
            print(
                f"{name} / TCP side by side, {mode}: p50 {p50:.2f} / {base:.2f} ms = x{p50 / base:.2f} "
                f"({p50 - base:+.2f} ms), p99 {p99:.2f} / {base99:.2f} ms = x{p99 / base99:.2f}"
            )

    floor = rows[-1][1]
    for index, label in ((0, "openral TCP"), (5, "remote_policy skill")):
        paced, back_to_back = rows[index][1]
        share = float(np.percentile(paced, 50) - np.percentile(floor[0], 50))
        share_b2b = float(np.percentile(back_to_back, 50) - np.percentile(floor[1], 50))
        print(f"openral's share ({label} p50 - Zenoh alone p50): paced {share:.2f} ms, back to back {share_b2b:.2f} ms")
    print(f"server SIGKILLed -> client knows it is down: {' '.join(f'{ms:.1f}' for ms in detection)} ms")


if __name__ == "__main__":
    main()
