"""``openpi_policy``: chunks from an openpi-protocol server, its failures, and the unmodified openpi-server."""

import json
import socket
import ssl
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from openral_core import (
    FrameEncoding,
    JointState,
    PrivilegedState,
    RobotManifest,
    ROSConfigError,
    ROSSkillError,
    SensorFrame,
    WorldState,
)
from openral_hal.manifests import load_robot_manifest
from openral_remote.msgpack_numpy import packb, unpackb
from openral_remote.openpi_skill import OpenpiPolicySkill, OpenpiTimeout, OpenpiUnavailable
from openral_remote.testing import wait_for
from openral_rskill.anchoring import AbsoluteAnchor, EndEffectorDeltaAnchor
from openral_rskill.chunks import ChunkRequest

pytest.importorskip("websockets", reason="needs the 'remote' extra")
from websockets.sync.server import ServerConnection, serve

ROOT = Path(__file__).resolve().parents[2]
Answer = Callable[[dict[str, Any]], bytes | str | None]


class FakeServer:
    """An openpi-protocol server in a thread: the metadata frame, then ``answer(obs)`` per request (``None``: none)."""

    def __init__(self, metadata: dict[str, Any], answer: Answer, ssl_context: ssl.SSLContext | None = None) -> None:
        self.metadata = metadata
        self.answer = answer
        self.requests: list[dict[str, Any]] = []
        self.headers: list[str | None] = []
        self.connections = 0
        self._server = serve(self._handle, "127.0.0.1", 0, compression=None, max_size=None, ssl=ssl_context)
        self.port = self._server.socket.getsockname()[1]
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self._thread.start()

    def _handle(self, ws: ServerConnection) -> None:
        self.connections += 1
        assert ws.request is not None
        self.headers.append(ws.request.headers.get("Authorization"))
        ws.send(packb(self.metadata))
        for message in ws:
            obs = unpackb(message)  # type: ignore[arg-type]
            self.requests.append(obs)
            reply = self.answer(obs)
            if reply is None:
                continue
            ws.send(reply)
            if isinstance(reply, str):
                ws.close(1011, "Internal server error. Traceback included in previous frame.")
                return

    def close(self) -> None:
        self._server.shutdown()
        self._thread.join(timeout=10)


@pytest.fixture
def fake_server() -> Iterator[Callable[..., FakeServer]]:
    made: list[FakeServer] = []

    def start(metadata: dict[str, Any], answer: Answer, ssl_context: ssl.SSLContext | None = None) -> FakeServer:
        made.append(FakeServer(metadata, answer, ssl_context))
        return made[-1]

    yield start
    for server in made:
        server.close()


def _chunk(horizon: int, width: int) -> Answer:
    """Row j of every chunk is j + column/10, as float32."""
    rows = (np.arange(horizon)[:, None] + np.arange(width)[None, :] / 10).astype(np.float32)
    return lambda _obs: packb({"actions": rows, "server_timing": {"infer_ms": 0.1}})


def _robot() -> RobotManifest:
    return load_robot_manifest("so101_follower")


def _world(task: str = "pick up the cube") -> WorldState:
    names = _robot().joint_names
    return WorldState(
        stamp_ns=1,
        joint_state=JointState(names=names, positions=[0.1 * i for i in range(len(names))]),
        privileged=PrivilegedState(values={"target_pos": [0.2, 0.0, 0.05]}),
        task=task,
    )


def _skill(port: int, **params: Any) -> OpenpiPolicySkill:
    return OpenpiPolicySkill.from_config({"port": port, **params}, robot=_robot(), rate_hz=30.0)


def _active(skill: OpenpiPolicySkill) -> OpenpiPolicySkill:
    skill.configure()
    skill.activate()
    return skill


def test_chunks_come_from_the_server_sliced_to_rows_and_columns(fake_server) -> None:  # type: ignore[no-untyped-def]
    server = fake_server({"action_horizon": 10, "action_dim": 8}, _chunk(10, 8))
    skill = _active(_skill(server.port, rows=5, action_slice=[1, 7], representation="absolute", api_key="k3y"))
    try:
        chunk = skill.step_chunk(ChunkRequest(_world()))
        assert chunk.shape == (5, 6)
        assert chunk.dtype == np.float64
        np.testing.assert_allclose(chunk[2], 2 + np.arange(1, 7) / 10, rtol=1e-6)
        obs = server.requests[-1]
        assert sorted(obs) == [
            "observation/joint_names",
            "observation/privileged/target_pos",
            "observation/state",
            "prompt",
        ]
        np.testing.assert_allclose(obs["observation/state"], [0.1 * i for i in range(6)])
        assert server.headers[-1] == "Api-Key k3y"
        assert skill.info.chunk_size == 5
        assert isinstance(skill.action_anchor(), AbsoluteAnchor)
    finally:
        skill.shutdown()


def _openral_meta(**changes: Any) -> dict[str, Any]:
    meta = {
        "policy": "pick",
        "robot": "so101_follower",
        "skill_id": "onnx_policy",
        "chunk_size": 8,
        "action_names": _robot().joint_names,
        "control_mode": "ee_delta",
        "anchor": {"representation": "delta_ee", "position_key": "target_pos", "scale": 0.025},
        "dt_s": 1 / 30,
        "observation": ["joint_state"],
        "model_hash": "ab" * 32,
    }
    return {**meta, **changes}


def test_rows_and_anchor_come_from_openral_metadata_when_params_leave_them(fake_server) -> None:  # type: ignore[no-untyped-def]
    meta = _openral_meta()
    server = fake_server({"action_horizon": 8, "action_dim": 6, "openral": meta}, _chunk(8, 6))
    skill = _active(_skill(server.port))
    try:
        assert skill.info.chunk_size == 8
        assert isinstance(skill.action_anchor(), EndEffectorDeltaAnchor)
        assert skill.step_chunk(ChunkRequest(_world())).shape == (8, 6)
        assert sorted(server.requests[-1]) == ["observation/joint_names", "observation/state"]  # what it reads
    finally:
        skill.shutdown()


def test_build_refuses_what_the_server_says_does_not_fit(fake_server) -> None:  # type: ignore[no-untyped-def]
    server = fake_server({"action_horizon": 4, "action_dim": 9}, _chunk(4, 9))
    with pytest.raises(ROSSkillError, match=r"vla\.params\.rows: rows 5 exceeds the server's action_horizon 4"):
        _skill(server.port, rows=5, representation="absolute", action_slice=[0, 6]).configure()
    with pytest.raises(ROSSkillError, match="actions are 9 wide, robot so101_follower takes 6"):
        _skill(server.port, rows=4, representation="absolute").configure()
    with pytest.raises(ROSConfigError, match=r"vla\.params\.host: .*cannot reach"):
        _skill(_free_port(), rows=4)


def test_a_dead_server_marks_the_link_down_and_it_comes_back(fake_server) -> None:  # type: ignore[no-untyped-def]
    server = fake_server({"action_horizon": 8, "action_dim": 6}, _chunk(8, 6))
    port = server.port
    skill = _active(_skill(port, rows=8, representation="absolute", reconnect_s=0.05, connect_timeout_s=2))
    try:
        assert skill.available()
        server.close()
        with pytest.raises(OpenpiUnavailable):  # passed through without a latch: the next step may succeed
            skill.step_chunk(ChunkRequest(_world()))
        assert not skill.available()
        assert skill.state.value == "active"
        revived = FakeServer({"action_horizon": 8, "action_dim": 6}, _chunk(8, 6))
        try:
            _restart_on(revived, port)
            assert wait_for(skill.available, timeout_s=20)
            assert skill.step_chunk(ChunkRequest(_world())).shape == (8, 6)
        finally:
            revived.close()
    finally:
        skill.shutdown()


def test_a_server_back_with_another_model_is_refused_and_a_restart_is_taken_back(fake_server) -> None:  # type: ignore[no-untyped-def]
    server = fake_server({"action_horizon": 8, "action_dim": 6, "openral": _openral_meta(warmup_ms=1.0)}, _chunk(8, 6))
    port = server.port
    skill = _active(_skill(port, reconnect_s=0.05, connect_timeout_s=2))
    try:
        server.close()
        with pytest.raises(OpenpiUnavailable):
            skill.step_chunk(ChunkRequest(_world()))
        other = FakeServer(
            {"action_horizon": 8, "action_dim": 6, "openral": _openral_meta(model_hash="cd" * 32)}, _chunk(8, 6)
        )
        try:
            _restart_on(other, port)
            assert wait_for(lambda: skill.available() or other.connections >= 3, timeout_s=20)
            assert not skill.available()  # asked again and again, never taken
        finally:
            other.close()
        restarted = FakeServer(
            {"action_horizon": 8, "action_dim": 6, "openral": _openral_meta(warmup_ms=7.0)}, _chunk(8, 6)
        )
        try:
            _restart_on(restarted, port)
            assert wait_for(skill.available, timeout_s=20)
        finally:
            restarted.close()
    finally:
        skill.shutdown()


def test_a_server_that_drops_each_connection_at_once_is_unavailable_not_a_crash() -> None:
    """Whether the client's reader has already closed the socket or not, the answer is one config error."""

    def drop(ws: ServerConnection) -> None:
        ws.socket.shutdown(socket.SHUT_RDWR)

    with serve(drop, "127.0.0.1", 0) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        port = server.socket.getsockname()[1]
        for rows in (None, 8) * 10:  # asked for its rows at start-up, or only when configured
            fixed = {} if rows is None else {"rows": rows, "representation": "absolute"}
            with pytest.raises((ROSConfigError, ROSSkillError), match=r"vla\.params\.host: the openpi server at ws://"):
                _skill(port, connect_timeout_s=2, **fixed).configure()
        server.shutdown()


def test_a_silent_server_is_late_and_the_link_is_dropped(fake_server) -> None:  # type: ignore[no-untyped-def]
    server = fake_server({"action_horizon": 8, "action_dim": 6}, lambda _obs: None)
    skill = _active(_skill(server.port, rows=8, representation="absolute", deadline_ms=200, reconnect_s=60))
    try:
        started = time.monotonic()
        with pytest.raises(OpenpiTimeout):
            skill.step_chunk(ChunkRequest(_world()))
        assert time.monotonic() - started < 5
        assert not skill.available()
    finally:
        skill.shutdown()


class DeafServer:
    """Completes the websocket handshake and sends the metadata, then never reads again (a wedged server)."""

    def __init__(self, metadata: dict[str, Any]) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.metadata = metadata
        self.accepted: list[socket.socket] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        import base64  # noqa: PLC0415
        import hashlib  # noqa: PLC0415

        conn, _ = self.listener.accept()
        self.accepted.append(conn)
        request = b""
        while b"\r\n\r\n" not in request:
            request += conn.recv(4096)
        key = next(
            line.split(b":", 1)[1].strip()
            for line in request.split(b"\r\n")
            if line.lower().startswith(b"sec-websocket-key")
        )
        accept = base64.b64encode(hashlib.sha1(key + b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11").digest())
        conn.sendall(
            b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"Sec-WebSocket-Accept: " + accept + b"\r\n\r\n"
        )
        body = packb(self.metadata)
        assert len(body) < 126
        conn.sendall(bytes([0x82, len(body)]) + body)  # one unmasked binary frame

    def close(self) -> None:
        for conn in self.accepted:
            conn.close()
        self.listener.close()


def test_a_server_that_stops_reading_cannot_wedge_the_request() -> None:
    server = DeafServer({"action_horizon": 8, "action_dim": 6})
    skill = _active(_skill(server.port, profile="openral", rows=8, representation="absolute", deadline_ms=300))
    try:
        big = np.zeros((4000, 4000, 3), np.uint8)  # 48 MB: more than the socket buffers hold
        frame = SensorFrame(
            sensor_id="front", stamp_ns=1, width=4000, height=4000, encoding=FrameEncoding.RGB8, data=big
        )
        world = _world().model_copy(update={"image_frames": {"front": frame}})
        started = time.monotonic()
        with pytest.raises(OpenpiUnavailable):
            skill.step_chunk(ChunkRequest(world))
        assert time.monotonic() - started < 10
        assert not skill.available()
    finally:
        skill.shutdown()
        server.close()


def test_a_text_frame_is_the_servers_error(fake_server) -> None:  # type: ignore[no-untyped-def]
    server = fake_server({"action_horizon": 8, "action_dim": 6}, lambda _obs: "Traceback ...\nValueError: bad obs")
    skill = _active(_skill(server.port, rows=8, representation="absolute"))
    try:
        with pytest.raises(ROSSkillError, match="ValueError: bad obs"):
            skill.step_chunk(ChunkRequest(_world()))
        assert not skill.available()
    finally:
        skill.shutdown()


def test_each_episode_is_a_new_connection(fake_server) -> None:  # type: ignore[no-untyped-def]
    server = fake_server({"action_horizon": 8, "action_dim": 6}, _chunk(8, 6))
    skill = _active(_skill(server.port, rows=8, representation="absolute"))
    try:
        before = server.connections
        skill.reset(seed=3)
        assert server.connections == before + 1
        assert skill.step_chunk(ChunkRequest(_world())).shape == (8, 6)
    finally:
        skill.shutdown()


def test_the_libero_profile_checks_the_robot_and_sends_its_images(fake_server) -> None:  # type: ignore[no-untyped-def]
    server = fake_server({"action_horizon": 10, "action_dim": 7}, _chunk(10, 7))
    skill = _skill(server.port, profile="libero", rows=5, representation="absolute", action_slice=[0, 6])
    assert skill.info.observation == ["joint_state", "images.agentview", "images.robot0_eye_in_hand", "task"]
    with pytest.raises(ROSConfigError, match=r"vla\.params\.profile: the libero profile sends a state of 8 values"):
        skill.check_robot_inputs()
    _active(skill)
    try:
        image = np.zeros((256, 256, 3), np.uint8)
        frames = {
            name: SensorFrame(
                sensor_id=name, stamp_ns=1, width=256, height=256, encoding=FrameEncoding.RGB8, data=image
            )
            for name in ("agentview", "robot0_eye_in_hand")
        }
        world = WorldState(
            stamp_ns=1,
            joint_state=JointState(names=[f"s{i}" for i in range(8)], positions=[0.0] * 8),
            image_frames=frames,
            task="put the bowl on the plate",
        )
        assert skill.step_chunk(ChunkRequest(world)).shape == (5, 6)
        obs = server.requests[-1]
        assert obs["observation/image"].shape == (224, 224, 3)
        assert obs["prompt"] == "put the bowl on the plate"
    finally:
        skill.shutdown()


def test_wss_with_the_servers_ca(fake_server, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from openral_remote.testing_tls import make_ca, make_certificate  # noqa: PLC0415

    ca = make_ca(tmp_path / "ca")
    issued = make_certificate(tmp_path / "server", "policy-server", ca)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(issued.cert, issued.key)
    server = fake_server({"action_horizon": 8, "action_dim": 6}, _chunk(8, 6), context)
    params = {"rows": 8, "representation": "absolute", "connect_timeout_s": 5}
    skill = _active(_skill(server.port, tls={"ca": str(ca.cert)}, **params))
    try:
        assert skill.step_chunk(ChunkRequest(_world())).shape == (8, 6)
    finally:
        skill.shutdown()
    stranger = make_ca(tmp_path / "other", "another CA")
    with pytest.raises(ROSSkillError, match="CERTIFICATE_VERIFY_FAILED"):
        _active(_skill(server.port, tls={"ca": str(stranger.cert)}, **params))
    with pytest.raises(ROSSkillError, match="refused the websocket"):  # a plain client of a TLS server
        _active(_skill(server.port, **params))


def test_parameters_are_checked_without_a_server() -> None:
    robot = _robot()
    with pytest.raises(ROSConfigError, match=r"vla\.params\.cameras: the aloha profile has no camera slot 'cam_side'"):
        OpenpiPolicySkill.check_config({"profile": "aloha", "cameras": {"cam_side": "x"}}, robot=robot, rate_hz=30)
    with pytest.raises(ROSConfigError, match=r"vla\.params\.action_slice: .*takes 3 columns"):
        OpenpiPolicySkill.check_config({"action_slice": [0, 3]}, robot=robot, rate_hz=30)
    with pytest.raises(ROSConfigError, match=r"vla\.params\.tls\.ca"):
        OpenpiPolicySkill.check_config({"tls": {"ca": "/nonexistent/ca.pem"}}, robot=robot, rate_hz=30)
    with pytest.raises(ROSConfigError, match="anchor_key"):
        OpenpiPolicySkill.check_config({"representation": "delta_ee"}, robot=robot, rate_hz=30)
    with pytest.raises(ROSConfigError, match=r"vla\.params\.profile: the libero profile sends a state of 8 values"):
        OpenpiPolicySkill.check_config({"profile": "libero"}, robot=robot, rate_hz=30)
    OpenpiPolicySkill.check_config({"profile": "openral", "port": 1}, robot=robot, rate_hz=30)


_DEPLOYMENT = """
name: openpi_validate
rate_hz: 30
hal: {robot_id: ROBOT, adapter: null}
vla:
  id: openpi_policy
  params: PARAMS
task: {instruction: pick up the cube}
safety: {client: envelope, mode: clamp}
"""


def _validate(tmp_path: Path, robot: str, params: dict[str, Any]) -> Any:
    from click.testing import CliRunner  # noqa: PLC0415

    from openral_cli.main import cli  # noqa: PLC0415

    path = tmp_path / "deployment.yaml"
    path.write_text(_DEPLOYMENT.replace("ROBOT", robot).replace("PARAMS", json.dumps(params)), encoding="utf-8")
    return CliRunner().invoke(cli, ["validate", str(path)])


def test_validate_checks_the_profile_against_the_deployment_without_connecting(tmp_path: Path) -> None:
    with socket.socket() as listener:  # where the file says the server is: it must never be called
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        listener.setblocking(False)
        port = listener.getsockname()[1]
        ok = _validate(tmp_path, "so101_follower", {"port": port, "connect_timeout_s": 600})
        assert ok.exit_code == 0, ok.output
        cameras = _validate(tmp_path, "aloha_bimanual_viperx", {"port": port, "profile": "aloha"})
        assert cameras.exit_code == 2, cameras.output
        assert "reads camera(s) ['top'], which the deployment does not have" in cameras.output
        state = _validate(tmp_path, "so101_follower", {"port": port, "profile": "droid"})
        assert state.exit_code == 2, state.output
        assert "vla.params.profile: the droid profile sends a state of 8 values" in state.output
        with pytest.raises(BlockingIOError):
            listener.accept()


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _restart_on(server: FakeServer, port: int) -> None:
    """Move ``server`` onto ``port`` (the dead server's), so the skill's next try reaches it."""
    server._server.shutdown()
    server._thread.join(timeout=10)
    server._server = serve(server._handle, "127.0.0.1", port, compression=None, max_size=None)
    server.port = port
    server._thread = threading.Thread(target=server._server.serve_forever, daemon=True)
    server._thread.start()


# --- end to end: the unmodified openpi-server hosting the ONNX pick policy --------------------------

_HOST_ONNX = """
import json, os, sys, time
import numpy as np, onnxruntime as ort
from openpi_server import WebsocketPolicyServer

model, port, extra = sys.argv[1], int(sys.argv[2]), json.loads(sys.argv[3])
die_after, hang_after = extra.pop("__die_after__", None), extra.pop("__hang_after__", None)
answered = 0
session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
custom = session.get_modelmeta().custom_metadata_map
fields = json.loads(custom["openral.observation"])
horizon, width = int(custom["chunk_size"]), len(json.loads(custom["action"]))
name = session.get_inputs()[0].name

class Policy:
    def infer(self, obs):
        global answered
        if die_after is not None and answered >= die_after:
            os._exit(3)
        if hang_after is not None and answered >= hang_after:
            time.sleep(3600)  # blocks openpi-server's event loop: silent, handshakes included
        answered += 1
        parts = []
        for field in fields:
            if field == "joint_state":
                parts.append(obs["observation/state"])
            else:
                parts.append(obs["observation/privileged/" + field.removeprefix("privileged.")])
        x = np.concatenate([np.asarray(p, dtype=np.float32) for p in parts])[None, :]
        (out,) = session.run(None, {name: x})
        return {"actions": np.asarray(out, dtype=np.float32).reshape(horizon, width)}

metadata = {"action_horizon": horizon, "action_dim": width, **extra}
WebsocketPolicyServer(Policy(), host="127.0.0.1", port=port, metadata=metadata).serve_forever()
"""


def _healthy(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=1) as sock:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            return sock.recv(64).startswith(b"HTTP/1.1 200")
    except OSError:
        return False


def _sim_run(skill: str, params: dict[str, Any], n: int, scene: Path | None = None, expect: int = 0) -> dict[str, Any]:
    """``openral sim run --json`` (no cameras): its report, or ``{"stderr": ...}`` when it fails with ``expect``."""
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "openral_cli",
            "sim",
            "run",
            "--config",
            str(scene or ROOT / "scenes/sim/so101_pick.yaml"),
            "--skill",
            skill,
            "--skill-params",
            json.dumps(params),
            "--n-episodes",
            str(n),
            "--no-cameras",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
        cwd=ROOT,
    )
    assert done.returncode == expect, done.stderr[-3000:]
    return json.loads(done.stdout) if expect == 0 else {"stderr": done.stderr}  # type: ignore[no-any-return]


def _outcomes(report: dict[str, Any]) -> list[tuple[int, bool, int]]:
    return [(e["seed"], e["success"], e["steps"]) for e in report["episodes"]]


@pytest.fixture
def openpi_server(peer_venv) -> Iterator[Callable[[dict[str, Any]], int]]:  # type: ignore[no-untyped-def]
    """``start(metadata)``: the unmodified openpi-server 0.1.0 hosting the committed ONNX pick policy; its port."""
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    peer = peer_venv("openpi-server", "onnxruntime")
    started: list[subprocess.Popen[str]] = []

    def start(extra: dict[str, Any]) -> int:
        port = _free_port()
        proc = peer.popen(
            _HOST_ONNX, str(ROOT / "models/so101_pick_mlp.onnx"), str(port), json.dumps(extra), stderr=subprocess.PIPE
        )
        started.append(proc)
        assert wait_for(lambda: _healthy(port) or proc.poll() is not None, timeout_s=60)
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        return port

    yield start
    for proc in started:
        if proc.poll() is None:
            proc.kill()  # it may be blocked in its event loop (a hanging policy): no clean shutdown to wait for
        proc.communicate(timeout=10)


def _served_meta() -> dict[str, Any]:
    """What an openral server would put under ``openral``: the local skill's meta, as the sim builds it."""
    from openral_core import SimEnvironment  # noqa: PLC0415
    from openral_remote.meta import describe  # noqa: PLC0415
    from openral_sim.build import build_skill  # noqa: PLC0415
    from openral_sim.env import make_env  # noqa: PLC0415

    scene = SimEnvironment.from_yaml(ROOT / "scenes/sim/so101_pick.yaml").model_copy(update={"cameras": []})
    env = make_env(scene)
    try:
        skill = build_skill(scene, env.spec, "onnx_policy", {"model": str(ROOT / "models/so101_pick_mlp.onnx")})
        meta = describe(
            skill,
            policy="pick",
            robot="so101_pick",
            action_names=list(env.spec.action_names),
            rate_hz=env.spec.control_hz,
            model_hash="0" * 64,
        )
    finally:
        env.close()
    return meta.model_dump(mode="json")


@pytest.mark.slow
@pytest.mark.timeout(600)  # three simulated runs, on a shared 2-core machine
def test_sim_run_against_the_unmodified_openpi_server_matches_the_local_run(openpi_server) -> None:  # type: ignore[no-untyped-def]
    n = 10
    local = _sim_run("onnx_policy", {"model": str(ROOT / "models/so101_pick_mlp.onnx")}, n)
    with_meta = _sim_run("openpi_policy", {"port": openpi_server({"openral": _served_meta()})}, n)
    plain = _sim_run(
        "openpi_policy",
        {
            "port": openpi_server({}),
            "rows": 8,
            "representation": "delta_ee",
            "anchor_key": "target_pos",
            "action_scale": 0.025,
        },
        n,
    )
    assert 0 < local["n_success"] < n  # a comparison that can tell successes from failures
    assert _outcomes(with_meta) == _outcomes(local)
    assert _outcomes(plain) == _outcomes(local)


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.parametrize("failure", ["__die_after__", "__hang_after__"])
def test_a_server_that_dies_or_hangs_mid_run_hands_over_to_the_fallback(
    openpi_server,
    tmp_path: Path,  # type: ignore[no-untyped-def]
    failure: str,
) -> None:
    scene = (
        (ROOT / "scenes/sim/so101_pick.yaml")
        .read_text(encoding="utf-8")
        .replace(
            "executor: {margin_ticks: 5}",
            "executor: {margin_ticks: 5, fallback: skill, fallback_skill: {id: so101_pick_expert}}",
        )
    )
    path = tmp_path / "so101_pick.yaml"
    path.write_text(scene, encoding="utf-8")
    port = openpi_server({failure: 3})  # answers three chunks, then exits or stops answering
    params = {
        "port": port,
        "rows": 8,
        "representation": "delta_ee",
        "anchor_key": "target_pos",
        "action_scale": 0.025,
        "connect_timeout_s": 1,
        "deadline_ms": 500,
        "reconnect_s": 0.2,
    }
    started = time.monotonic()
    report = _sim_run("openpi_policy", params, 3, scene=path)
    assert len(report["episodes"]) == 3  # the run completes
    # The server gave 3 chunks of 8 rows; an episode that succeeds later did so on the fallback expert.
    assert [e for e in report["episodes"] if e["success"] and e["steps"] > 24]
    assert time.monotonic() - started < 300


def test_a_server_that_is_not_there_at_start_up_is_named(tmp_path: Path) -> None:
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    params = {"port": _free_port(), "rows": 8, "representation": "absolute", "connect_timeout_s": 1}
    done = _sim_run("openpi_policy", params, 1, expect=2)
    assert "params.host" in done["stderr"]
    assert "cannot reach the openpi server" in done["stderr"]
