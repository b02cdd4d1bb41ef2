"""``openral serve --protocol openpi`` against the unmodified openpi-client 0.1.2 (its own venv, numpy 1.x).

The golden fixture ``fixtures/openpi_libero_obs.msgpack`` is what openpi-client packed for a small
LIBERO-shaped observation: openral decodes it and re-encodes it byte for byte; a test regenerates
it with the real package and compares.
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from openral_remote.msgpack_numpy import packb, unpack_tree, unpackb
from openral_remote.openpi_profiles import OpenpiProfile
from openral_remote.testing import wait_for

pytestmark = pytest.mark.timeout(300)

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).parent / "fixtures" / "openpi_libero_obs.msgpack"
SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"
MODEL = {"model": str(ROOT / "models" / "so101_pick_mlp.onnx")}

_GOLDEN_PACK = """
import sys, numpy as np
from openpi_client import msgpack_numpy
obs = {
    "observation/image": np.arange(32 * 32 * 3, dtype=np.uint8).reshape(32, 32, 3),
    "observation/wrist_image": np.full((32, 32, 3), 9, dtype=np.uint8),
    "observation/state": np.linspace(-1, 1, 8, dtype=np.float32),
    "prompt": "put the bowl on the plate",
}
sys.stdout.buffer.write(msgpack_numpy.packb(obs))
"""


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _healthy(port: int, server: subprocess.Popen[str]) -> bool:
    assert server.poll() is None, f"openral serve exited: {server.communicate()[1][-3000:]}"
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as response:
            return bool(response.status == 200)
    except (urllib.error.URLError, ConnectionError, TimeoutError):
        return False


@contextlib.contextmanager
def _serving(*args: str) -> Iterator[int]:
    """``openral serve --protocol openpi ARGS`` on a free loopback port, ready (``/healthz``); stopped with SIGINT."""
    port = _free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "openral_cli", "serve", "--protocol", "openpi", "--listen", f"127.0.0.1:{port}", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert wait_for(lambda: _healthy(port, server), timeout_s=120)
        yield port
    finally:
        server.send_signal(signal.SIGINT)
        _out, err = server.communicate(timeout=60)
    assert server.returncode == 0, err[-3000:]
    assert "served " in err  # its closing summary


def test_the_golden_openpi_bytes_decode_and_reencode_identically() -> None:
    golden = GOLDEN.read_bytes()
    obs = unpackb(golden)
    assert obs["observation/image"].dtype == np.uint8
    assert obs["observation/state"].dtype == np.float32
    assert packb(obs) == golden
    profile = OpenpiProfile("libero", image_size=32)
    profile.check(unpack_tree(golden))
    world = profile.world(obs, stamp_ns=1)
    assert world.task == "put the bowl on the plate"
    assert world.joint_state is not None
    assert len(world.joint_state.positions) == 8
    agentview = (world.image_frames or {})["agentview"].data
    assert isinstance(agentview, np.ndarray)
    np.testing.assert_array_equal(agentview, obs["observation/image"][:, ::-1])  # the example's rotation undone


@pytest.mark.slow
def test_the_unmodified_openpi_client_still_packs_the_golden_bytes(peer_venv: Any) -> None:
    regenerated = peer_venv("openpi-client").run(_GOLDEN_PACK, text=False).stdout
    assert regenerated == GOLDEN.read_bytes()


_HELLO_CLIENT = """
import json, sys, numpy as np
from openpi_client.websocket_client_policy import WebsocketClientPolicy
from openpi_client.action_chunk_broker import ActionChunkBroker
port, key = int(sys.argv[1]), (sys.argv[2] or None)
policy = WebsocketClientPolicy(host="127.0.0.1", port=port, api_key=key)
meta = policy.get_server_metadata()
obs = {"observation/state": np.zeros(6), "prompt": "wave"}
actions = policy.infer(obs)["actions"]
broker = ActionChunkBroker(policy, action_horizon=meta["action_horizon"])
row = broker.infer(obs)["actions"]
print(json.dumps({"horizon": meta["action_horizon"], "dim": meta["action_dim"], "robot": meta["openral"]["robot"],
                  "shape": list(actions.shape), "dtype": str(actions.dtype), "row": list(row.shape)}))
"""


@pytest.mark.slow
def test_the_unmodified_openpi_client_gets_chunks_of_a_hello_skill(peer_venv: Any) -> None:
    peer = peer_venv("openpi-client")
    with _serving("--skill", "hello", "--skill-params", '{"chunk_size": 15}', "--robot", "so101_follower") as port:
        out = json.loads(peer.run(_HELLO_CLIENT, str(port), "").stdout.splitlines()[-1])
    assert out == {"horizon": 15, "dim": 6, "robot": "so101_follower", "shape": [15, 6], "dtype": "float32", "row": [6]}


_PICK_CLIENT = """
import sys
from openpi_client import msgpack_numpy
from openpi_client.websocket_client_policy import WebsocketClientPolicy
policy = WebsocketClientPolicy(host="127.0.0.1", port=int(sys.argv[1]))
meta = policy.get_server_metadata()
actions = policy.infer(msgpack_numpy.unpackb(sys.stdin.buffer.read()))["actions"]
sys.stdout.buffer.write(msgpack_numpy.packb({"meta": meta, "actions": actions}))
"""


@pytest.mark.slow
def test_the_unmodified_openpi_client_gets_the_onnx_pick_policys_chunk(peer_venv: Any) -> None:
    from openral_core import JointState, PrivilegedState, SimEnvironment, WorldState  # noqa: PLC0415
    from openral_rskill.chunks import ChunkRequest  # noqa: PLC0415
    from openral_runner.factory import SKILL_REGISTRY  # noqa: PLC0415
    from openral_sim.env import make_env  # noqa: PLC0415

    scene = SimEnvironment.from_yaml(SCENE)
    env = make_env(scene)
    try:
        first = env.reset(seed=3)
        spec = env.spec
    finally:
        env.close()
    names = [f"q{i}" for i in range(first.state.size)]
    world = WorldState(
        stamp_ns=1,
        joint_state=JointState(names=names, positions=first.state.tolist()),
        privileged=PrivilegedState(values=first.privileged),
    )
    local = SKILL_REGISTRY.resolve("onnx_policy", field="skill").from_config(
        MODEL, robot=spec.action_manifest(scene.robot or scene.env), rate_hz=spec.control_hz
    )
    local.configure()
    local.activate()
    expected = local.step_chunk(ChunkRequest(world))
    local.shutdown()
    obs = packb(OpenpiProfile("openral", image_size=None).observation(world, reads=local.info.observation))

    peer = peer_venv("openpi-client")
    with _serving("--skill", "onnx_policy", "--skill-params", json.dumps(MODEL), "--scene", str(SCENE)) as port:
        reply = unpackb(peer.run(_PICK_CLIENT, str(port), input=obs, text=False).stdout)
    meta = reply["meta"]
    assert meta["action_horizon"] == expected.shape[0]
    assert meta["action_dim"] == expected.shape[1]
    assert meta["openral"]["anchor"]["representation"] == "delta_ee"
    assert meta["openral"]["observation"] == ["joint_state", "privileged.environment_state"]
    assert reply["actions"].dtype == np.float32
    np.testing.assert_allclose(reply["actions"], expected, rtol=1e-5, atol=1e-6)  # the local policy's chunk


_ERROR_CLIENT = """
import sys, numpy as np
from openpi_client.websocket_client_policy import WebsocketClientPolicy
robot = WebsocketClientPolicy(host="127.0.0.1", port=int(sys.argv[1]))
bad = WebsocketClientPolicy(host="127.0.0.1", port=int(sys.argv[1]))
robot.infer({"observation/state": np.zeros(6), "prompt": "x"})
try:
    bad.infer({"observation/state": np.zeros(4), "prompt": "x"})
except RuntimeError as exc:
    print("error:", str(exc).splitlines()[-1])
try:
    bad.infer({"observation/state": np.zeros(6), "prompt": "x"})
except Exception as exc:
    print("closed:", getattr(getattr(exc, "rcvd", None), "code", None))
print("robot:", robot.infer({"observation/state": np.zeros(6), "prompt": "x"})["actions"].shape)
"""


@pytest.mark.slow
def test_the_unmodified_openpi_client_sees_errors_and_the_others_keep_being_served(peer_venv: Any) -> None:
    peer = peer_venv("openpi-client")
    with _serving("--skill", "hello", "--skill-params", '{"chunk_size": 15}', "--robot", "so101_follower") as port:
        lines = peer.run(_ERROR_CLIENT, str(port)).stdout.splitlines()
    assert lines[0].startswith("error: refused: key 'observation/state': shape (4,)"), lines
    assert lines[1] == "closed: 1011", lines
    assert lines[2] == "robot: (15, 6)", lines


_NO_KEY_CLIENT = """
import sys
from openpi_client.websocket_client_policy import WebsocketClientPolicy
try:
    WebsocketClientPolicy(host="127.0.0.1", port=int(sys.argv[1]), api_key=sys.argv[2] or None)
except Exception as exc:
    print("refused:", exc)
"""


@pytest.mark.slow
def test_the_api_key_refuses_the_unmodified_client_without_it_and_serves_it_with_it(
    peer_venv: Any, tmp_path: Path
) -> None:
    key_file = tmp_path / "api.key"
    key_file.write_text("openral-test-key-0123\n")
    peer = peer_venv("openpi-client")
    hello = ("--skill", "hello", "--skill-params", '{"chunk_size": 15}', "--robot", "so101_follower")
    with _serving(*hello, "--api-key-file", str(key_file)) as port:
        without = peer.run(_NO_KEY_CLIENT, str(port), "", timeout=60).stdout
        wrong = peer.run(_NO_KEY_CLIENT, str(port), "openral-test-key-0124", timeout=60).stdout
        right = json.loads(peer.run(_HELLO_CLIENT, str(port), "openral-test-key-0123").stdout.splitlines()[-1])
    assert "refused:" in without
    assert "401" in without
    assert "refused:" in wrong
    assert "401" in wrong
    assert right["shape"] == [15, 6]
