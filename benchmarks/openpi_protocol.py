"""openpi's websocket protocol: ``openral serve --protocol openpi`` vs the unmodified openpi-server, and Zenoh.

One VGA RGB frame + a 6-d state in, a 50x6 float32 chunk out, loopback, in one run:

1. **One client**, at 30 Hz and back to back, p50/p99 of the round trip:
   * ``openral serve --protocol openpi --skill hello`` (chunk 50, SO-101's 6 joints: the command
     as shipped, the hello skill's own work included);
   * openral's openpi server (the class that command runs) and openpi-server 0.1.0, unmodified,
     in a venv of its own (numpy 1.x), each hosting a policy that returns a fixed 50x6 chunk;
   * openral's own Zenoh link (``openral_remote.testing``'s chunk server, the same chunk).
   The clients are asked in turn in every slot, so load drifts hit all alike. The openpi clients
   send the same bytes (openral's profile keys; openpi-server's policy ignores them).
2. **16 clients**, each its own process asking at ``--client-rate-hz``, against a stand-in policy
   whose inference takes ``--delay-ms`` (a GPU's time, not the CPU's): openral's openpi server
   with batching on (``max_batch`` 16, the same server class ``openral serve`` runs) vs
   openpi-server, which runs inference inside its event loop and so serves one request at a time.

Run:  uv run python benchmarks/openpi_protocol.py [--seconds 5] [--rate-hz 30] [--clients 16]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from _common import machine_line
from openral_core import FrameEncoding, JointState, SensorFrame, WorldState
from openral_hal.manifests import load_robot_manifest
from openral_remote.allocator import keep_message_memory
from openral_remote.client import RemotePolicyClient
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.msgpack_numpy import packb, unpackb
from openral_remote.testing import POLICY, ROBOT, free_endpoint

CHUNK, DIMS = 50, 6
PEER = ("openpi-server==0.1.0", "typing_extensions")
CLI = "openral serve --protocol openpi, hello skill"
OURS = "openral openpi server, fixed chunk"
THEIRS = "openpi-server 0.1.0, fixed chunk"

OPENPI_SERVER = """
import sys, time
import numpy as np
from openpi_server import WebsocketPolicyServer
port, delay_s = int(sys.argv[1]), float(sys.argv[2])

class Policy:
    def infer(self, obs):
        if delay_s:
            time.sleep(delay_s)
        return {"actions": np.zeros((50, 6), np.float32)}

    def reset(self):
        pass

metadata = {"action_horizon": 50, "action_dim": 6}
WebsocketPolicyServer(Policy(), host="127.0.0.1", port=port, metadata=metadata).serve_forever()
"""


def _peer_python() -> Path:
    """A venv with the unmodified openpi-server (cached under ``$XDG_CACHE_HOME/openral/bench``)."""
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "openral" / "bench"
    root = cache / "openpi-server-0.1.0"
    python = root / "bin" / "python"
    if not (root / ".complete").exists():
        uv = shutil.which("uv")
        if uv is None:
            raise SystemExit("this benchmark makes openpi-server's venv with uv: install uv")
        shutil.rmtree(root, ignore_errors=True)
        subprocess.run([uv, "venv", "--quiet", "--python", sys.executable, str(root)], check=True)
        subprocess.run([uv, "pip", "install", "--quiet", "--python", str(python), *PEER], check=True)
        (root / ".complete").write_text("\n".join(PEER) + "\n")
    return python


def _port() -> int:
    return int(free_endpoint().rsplit(":", 1)[1])


def _wait_healthy(port: int, process: subprocess.Popen[bytes], timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"the server on port {port} exited ({process.returncode})")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as response:
                if response.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            time.sleep(0.05)
    raise RuntimeError(f"the server on port {port} never answered /healthz")


def _stop(process: subprocess.Popen[bytes]) -> None:
    process.send_signal(signal.SIGINT)
    try:
        process.wait(30)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(10)


def _image() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, size=(480, 640, 3), dtype=np.uint8)


def _openpi_obs() -> dict[str, Any]:
    names = load_robot_manifest("so101_follower").joint_names
    return {
        "observation/images/front": _image(),
        "observation/state": np.full(DIMS, 0.1),
        "observation/joint_names": list(names),
        "prompt": "pick up the cube",
    }


class OpenpiClient:
    """openpi's client protocol (what openpi-client's ``WebsocketClientPolicy`` does), on openral's codec."""

    def __init__(self, url: str) -> None:
        from websockets.sync.client import connect  # noqa: PLC0415

        self.ws = connect(url, compression=None, max_size=None, open_timeout=30).__enter__()
        metadata = self.ws.recv(timeout=30)
        assert isinstance(metadata, bytes), metadata
        self.metadata = unpackb(metadata)
        self.obs = _openpi_obs()

    def infer(self) -> np.ndarray:
        self.ws.send(packb(self.obs))
        reply = self.ws.recv(timeout=30)
        if isinstance(reply, str):
            raise RuntimeError(reply)
        actions: np.ndarray = unpackb(reply)["actions"]
        return actions

    def close(self) -> None:
        self.ws.close()


def _zenoh_client(endpoint: str) -> tuple[RemotePolicyClient, WorldState]:
    client = RemotePolicyClient(
        PolicyKeys.of(ROBOT, POLICY), ZenohConfig(connect=[endpoint], shared_memory=False), deadline_ms=2000
    )
    client.connect(timeout_s=30)
    frame = SensorFrame(
        sensor_id="front", stamp_ns=1, width=640, height=480, encoding=FrameEncoding.RGB8, data=_image()
    )
    joints = JointState(names=[f"a{i}" for i in range(DIMS)], positions=[0.1] * DIMS)
    return client, WorldState(stamp_ns=1, joint_state=joints, image_frames={"front": frame})


def _percentiles(values: list[float]) -> str:
    return f"{np.percentile(values, 50):6.2f} / {np.percentile(values, 99):6.2f}"


def one_client(seconds: float, rate_hz: float, peer: Path) -> None:
    """The links, asked in turn in every 1/rate slot, then back to back."""
    cli_port, ours_port, theirs_port, zenoh_endpoint = _port(), _port(), _port(), free_endpoint()
    servers = [
        subprocess.Popen(
            [
                *(sys.executable, "-m", "openral_cli", "serve", "--protocol", "openpi", "--skill", "hello"),
                *("--skill-params", json.dumps({"chunk_size": CHUNK}), "--listen", f"127.0.0.1:{cli_port}"),
            ],
            stderr=subprocess.DEVNULL,
        ),
        subprocess.Popen(
            [sys.executable, __file__, "--openral-server", str(ours_port), "--delay-ms", "0", "--clients", "1"],
            stderr=subprocess.DEVNULL,
        ),
        subprocess.Popen([str(peer), "-c", OPENPI_SERVER, str(theirs_port), "0"], stderr=subprocess.DEVNULL),
        subprocess.Popen(
            [
                *(sys.executable, "-m", "openral_remote.testing", "--listen", zenoh_endpoint, "--dims", str(DIMS)),
                *("--chunk-size", str(CHUNK), "--rate-hz", str(rate_hz), "--observation", "all"),
            ],
        ),
    ]
    clients: dict[str, Callable[[], np.ndarray]] = {}
    closers: list[Callable[[], None]] = []
    try:
        for port, server in zip((cli_port, ours_port, theirs_port), servers, strict=False):
            _wait_healthy(port, server)
        for name, port in ((CLI, cli_port), (OURS, ours_port), (THEIRS, theirs_port)):
            client = OpenpiClient(f"ws://127.0.0.1:{port}")
            clients[name] = client.infer
            closers.append(client.close)
        zenoh, world = _zenoh_client(zenoh_endpoint)
        clients["openral Zenoh TCP, fixed chunk"] = lambda: zenoh.infer(world)
        closers.append(zenoh.close)
        for call in clients.values():
            assert call().shape == (CHUNK, DIMS)
            for _ in range(30):
                call()
        count = int(seconds * rate_hz)
        paced: dict[str, list[float]] = {name: [] for name in clients}
        back_to_back: dict[str, list[float]] = {name: [] for name in clients}
        start = time.perf_counter()
        for k in range(count):
            delay = start + k / rate_hz - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            for name, call in clients.items():
                began = time.perf_counter()
                call()
                paced[name].append((time.perf_counter() - began) * 1e3)
        for _ in range(count):
            for name, call in clients.items():
                began = time.perf_counter()
                call()
                back_to_back[name].append((time.perf_counter() - began) * 1e3)
    finally:
        for close in closers:
            close()
        for server in servers:
            _stop(server)
    print(
        f"\n1 client, VGA RGB + state in, {CHUNK}x{DIMS} out, {count} requests each ({rate_hz:g} Hz, then back to back)"
    )
    print(f"{'link':<46} {f'{rate_hz:g} Hz p50 / p99 ms':>22} {'back to back p50 / p99 ms':>28}")
    for name in clients:
        print(f"{name:<46} {_percentiles(paced[name]):>22} {_percentiles(back_to_back[name]):>28}")
    for label, series in (("paced", paced), ("back to back", back_to_back)):
        ratio = np.percentile(series[OURS], 50) / np.percentile(series[THEIRS], 50)
        print(f"openral / openpi-server p50 (same fixed chunk), {label}: {ratio:.2f}x")


def client_main(url: str, seconds: float, rate_hz: float) -> None:
    """One of the many clients: ask at ``rate_hz`` (catching up when late) for ``seconds``; print the round trips."""
    keep_message_memory()
    client = OpenpiClient(url)
    client.infer()
    print("ready", flush=True)
    sys.stdin.readline()  # every client starts together
    rtts: list[float] = []
    start = time.perf_counter()
    k = 0
    while time.perf_counter() - start < seconds:
        delay = start + k / rate_hz - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        began = time.perf_counter()
        client.infer()
        rtts.append((time.perf_counter() - began) * 1e3)
        k += 1
    client.close()
    print(json.dumps({"rtts": rtts, "asked": int(seconds * rate_hz)}), flush=True)


def _many(url: str, clients: int, seconds: float, rate_hz: float) -> list[dict[str, Any]]:
    procs = [
        subprocess.Popen(
            [sys.executable, __file__, "--client", url, "--seconds", str(seconds), "--client-rate-hz", str(rate_hz)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(clients)
    ]
    for proc in procs:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
    for proc in procs:
        assert proc.stdin is not None
        proc.stdin.write("go\n")
        proc.stdin.flush()
    results = []
    for proc in procs:
        out, _ = proc.communicate(timeout=seconds * 10 + 60)
        results.append(json.loads(out.strip().splitlines()[-1]))
    return results


def many_clients(clients: int, seconds: float, rate_hz: float, delay_ms: float, peer: Path) -> None:
    """``clients`` processes against each server in turn, the policy taking ``delay_ms`` per inference."""
    rows: list[tuple[str, list[dict[str, Any]]]] = []
    ours_port = _port()
    ours = subprocess.Popen(
        [
            sys.executable,
            __file__,
            "--openral-server",
            str(ours_port),
            "--delay-ms",
            str(delay_ms),
            "--clients",
            str(clients),
        ],
        stderr=subprocess.DEVNULL,
    )
    try:
        _wait_healthy(ours_port, ours)
        rows.append(
            (f"openral, batching on (max {clients})", _many(f"ws://127.0.0.1:{ours_port}", clients, seconds, rate_hz))
        )
    finally:
        _stop(ours)
    theirs_port = _port()
    theirs = subprocess.Popen(
        [str(peer), "-c", OPENPI_SERVER, str(theirs_port), str(delay_ms / 1e3)], stderr=subprocess.DEVNULL
    )
    try:
        _wait_healthy(theirs_port, theirs)
        rows.append(("openpi-server 0.1.0", _many(f"ws://127.0.0.1:{theirs_port}", clients, seconds, rate_hz)))
    finally:
        _stop(theirs)
    print(
        f"\n{clients} clients (one process each) asking at {rate_hz:g} Hz for {seconds:g} s, VGA RGB + state in, "
        f"{CHUNK}x{DIMS} out, inference {delay_ms:g} ms"
    )
    print(f"{'server':<34} {'asked/s':>8} {'served/s':>9} {'p50 / p99 ms':>18} {'per client min / max /s':>24}")
    for name, results in rows:
        served = [len(result["rtts"]) / seconds for result in results]
        rtts = [rtt for result in results for rtt in result["rtts"]]
        asked = sum(result["asked"] for result in results) / seconds
        spread = f"{min(served):.1f} / {max(served):.1f}"
        print(f"{name:<34} {asked:>8.0f} {sum(served):>9.0f} {_percentiles(rtts):>18} {spread:>24}")


def openral_server(port: int, delay_ms: float, max_batch: int) -> None:
    """openral's openpi server (the class ``openral serve --protocol openpi`` runs) of a stand-in batching policy."""
    from openral_remote.admission import ServeLimits  # noqa: PLC0415
    from openral_remote.openpi_profiles import OpenpiProfile  # noqa: PLC0415
    from openral_remote.openpi_server import OpenpiServer  # noqa: PLC0415
    from openral_remote.testing import ChunkSkill, chunk_meta  # noqa: PLC0415

    keep_message_memory()
    names = list(load_robot_manifest("so101_follower").joint_names)
    skill = ChunkSkill(names, chunk_size=CHUNK, delay_s=delay_ms / 1e3, observation=(), batch=max_batch)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with OpenpiServer(
        skill,
        meta=chunk_meta(skill, rate_hz=30.0, model_hash="bench"),
        profile=OpenpiProfile("openral", image_size=None, state_names=names),
        port=port,
        limits=ServeLimits(max_batch=max_batch, max_wait_ms=5.0),
    ):
        stop.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--rate-hz", type=float, default=30.0)
    parser.add_argument("--clients", type=int, default=16)
    parser.add_argument("--client-rate-hz", type=float, default=10.0)
    parser.add_argument(
        "--delay-ms", type=float, default=10.0, help="The stand-in policy's inference time (16 clients)."
    )
    parser.add_argument("--client", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--openral-server", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.client is not None:
        client_main(args.client, args.seconds, args.client_rate_hz)
        return
    if args.openral_server is not None:
        openral_server(args.openral_server, args.delay_ms, args.clients)
        return
    keep_message_memory()
    peer = _peer_python()
    print(machine_line())
    one_client(args.seconds, args.rate_hz, peer)
    many_clients(args.clients, args.seconds, args.client_rate_hz, args.delay_ms, peer)
    print(machine_line())


if __name__ == "__main__":
    main()
