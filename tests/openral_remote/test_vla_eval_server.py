"""``VlaEvalServer`` speaking vla-eval's protocol v1 (the messages as vla-eval 0.8.0 packs them), bounded and fair."""

from __future__ import annotations

import json
import socket
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Mapping
from typing import Any, ClassVar, Self

import msgpack
import numpy as np
import pytest
from click.testing import CliRunner
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import ClientConnection, connect

from openral_cli.main import EXIT_CONFIG, cli
from openral_cli.serve import VLA_EVAL_PROFILES
from openral_core import Action, ControlMode, JointSpec, RobotManifest, ROSConfigError, RSkillInfo, WorldState
from openral_remote.admission import ServeLimits
from openral_remote.meta import describe
from openral_remote.msgpack_numpy import packb
from openral_remote.vla_eval_server import PROFILES, VlaEvalServer
from openral_rskill.anchoring import Anchor, EndEffectorDeltaAnchor
from openral_rskill.base import RSkillBase
from openral_rskill.chunks import ChunkRequest

DIMS = 7
CHUNK = 4
ROBOT = RobotManifest(
    robot_id="libero",
    name="test",
    joints=[JointSpec(name=f"a{i}", lower=-1, upper=1, velocity_limit=20) for i in range(DIMS)],
)


class Echo(RSkillBase):
    """Row ``j`` of a chunk: ``[tick + j, seed, state[0], sees agentview, sees wrist, task length, chunk count]``."""

    INFO = RSkillInfo(skill_id="echo", control_mode=ControlMode.EE_DELTA, chunk_size=CHUNK)
    instances: ClassVar[list[Echo]] = []

    def __init__(self, observation: list[str] | None = None) -> None:
        super().__init__()
        self.chunks = 0
        self.seen: list[WorldState] = []
        self._info = self.INFO.model_copy(update={"observation": observation or []})
        Echo.instances.append(self)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls()

    @property
    def info(self) -> RSkillInfo:
        return self._info

    def serves_many_episodes(self) -> bool:
        return True

    def _step_impl(self, world_state: WorldState) -> Action:
        raise NotImplementedError

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        self.chunks += 1
        world = request.world
        self.seen.append(world)
        frames = world.image_frames or {}
        state = world.joint_state.positions[0] if world.joint_state is not None else -1.0
        row = [
            0.0,
            -1.0 if request.seed is None else float(request.seed),
            state,
            float("agentview" in frames),
            float("robot0_eye_in_hand" in frames),
            float(len(world.task or "")),
            float(self.chunks),
        ]
        rows = np.tile(row, (CHUNK, 1))
        rows[:, 0] = request.obs_tick + np.arange(CHUNK)
        return rows


class Delta(Echo):
    def action_anchor(self) -> Anchor:
        return EndEffectorDeltaAnchor("eef_pos", 0.05, [0, 1, 2], 1.0)


def make_server(skill: RSkillBase | None = None, **kwargs: Any) -> VlaEvalServer:
    skill = skill or Echo()
    meta = describe(
        skill, policy="echo", robot="libero", action_names=ROBOT.joint_names, rate_hz=20.0, model_hash="ab" * 32
    )
    kwargs.setdefault("profile", PROFILES["libero"])
    return VlaEvalServer(skill, meta=meta, port=0, **kwargs)


@pytest.fixture
def server() -> Iterator[VlaEvalServer]:
    with make_server() as running:
        yield running


def send(ws: ClientConnection, kind: str, payload: dict[str, Any], seq: int) -> None:
    ws.send(packb({"type": kind, "payload": payload, "seq": seq, "timestamp": time.time()}, dialect="vla_eval"))


def recv(ws: ClientConnection) -> dict[str, Any]:
    reply = msgpack.unpackb(ws.recv(timeout=10), raw=False)
    assert set(reply) == {"type", "payload", "seq", "timestamp"}
    return reply  # type: ignore[no-any-return]


def action(reply: dict[str, Any]) -> np.ndarray:
    assert reply["type"] == "action", reply
    encoded = reply["payload"]["actions"]
    assert encoded["__ndarray__"]
    assert encoded["dtype"] == "<f4"
    assert encoded["shape"] == [DIMS]
    return np.frombuffer(encoded["data"], dtype="<f4")


def observation(state0: float = 0.5, *, wrist: bool = True, task: str = "pick it") -> dict[str, Any]:
    images = {"agentview": np.full((16, 16, 3), 7, np.uint8)}
    if wrist:
        images["wrist"] = np.zeros((16, 16, 3), np.uint8)
    return {
        "images": images,
        "task_description": task,
        "states": np.array([state0, 0, 0, 0, 0, 0, 0.04, -0.04]),
        "controller_states": np.zeros(8, np.float32),
    }


def test_hello_announces_protocol_specs_and_the_policy(server: VlaEvalServer) -> None:
    with connect(server.url) as ws:
        send(ws, "hello", {"harness_version": "0.8.0", "protocol_version": 1}, 1)
        reply = recv(ws)
    assert reply["type"] == "hello"
    assert reply["seq"] == 1
    hello = reply["payload"]
    assert hello["protocol_version"] == 1
    assert hello["capabilities"] == {}
    assert hello["observation_params"] == {"send_state": True, "send_wrist_image": True}
    assert hello["action_spec"]["gripper"]["format"] == "binary_close_positive"
    assert hello["openral"]["model_hash"] == "ab" * 32
    assert hello["openral"]["chunk_size"] == CHUNK


def test_a_chunk_is_handed_out_one_row_per_observation_then_asked_again(server: VlaEvalServer) -> None:
    with connect(server.url) as ws:
        send(ws, "episode_start", {"task": {"name": "pick it", "episode_idx": 3}}, 1)
        rows = []
        for seq in range(2, 2 + CHUNK + 2):
            send(ws, "observation", observation(state0=seq), seq)
            reply = recv(ws)
            assert reply["seq"] == seq
            rows.append(action(reply))
        send(ws, "episode_end", {"metrics": {"success": False}, "steps": 6}, 99)
    rows_array = np.array(rows)
    np.testing.assert_array_equal(rows_array[:, 0], np.arange(CHUNK + 2))  # row j is for tick j
    np.testing.assert_array_equal(rows_array[:, 1], 3)  # seeded with the episode index
    np.testing.assert_array_equal(rows_array[:, 6], [1] * CHUNK + [2, 2])  # the policy ran twice
    np.testing.assert_array_equal(rows_array[:, 2], [2] * CHUNK + [2 + CHUNK] * 2)  # states -> joint state
    np.testing.assert_array_equal(rows_array[:, 3:5], 1)  # both cameras, the wrist under openral's name
    np.testing.assert_array_equal(rows_array[:, 5], len("pick it"))
    world = Echo.instances[-1].seen[0]
    assert world.joint_state is not None
    assert world.joint_state.names[0] == "eef_x"
    assert world.privileged is not None
    assert len(world.privileged.values["controller_states"]) == 8
    assert world.image_frames is not None
    np.testing.assert_array_equal(world.image_frames["agentview"].as_array(), 7)


def test_an_episode_start_drops_the_rest_of_the_chunk_and_reseeds(server: VlaEvalServer) -> None:
    with connect(server.url) as ws:
        send(ws, "episode_start", {"task": {"episode_idx": 0}}, 1)
        send(ws, "observation", observation(), 2)
        first = action(recv(ws))
        send(ws, "episode_start", {"task": {"episode_idx": 5}}, 3)
        send(ws, "observation", observation(), 4)
        second = action(recv(ws))
    assert first[0] == 0
    assert first[1] == 0
    assert second[0] == 0
    assert second[1] == 5
    assert second[6] == first[6] + 1


def test_bad_messages_get_an_error_with_their_seq_and_the_connection_keeps_serving(server: VlaEvalServer) -> None:
    huge = {"__image__": True, "format": "png", "data": b"x", "shape": [100_000, 100_000, 3]}
    lying = {"__ndarray__": True, "data": b"\0" * 8, "dtype": "<f8", "shape": [8]}
    with connect(server.url) as ws:
        ws.send(b"\xc1garbage")
        assert recv(ws)["type"] == "error"
        send(ws, "observation", {**observation(), "images": {"agentview": huge}}, 7)
        reply = recv(ws)
        assert reply["type"] == "error"
        assert reply["seq"] == 7
        assert "refused" in reply["payload"]["error"]
        send(ws, "observation", {**observation(), "states": lying}, 8)
        reply = recv(ws)
        assert reply["type"] == "error"
        assert reply["seq"] == 8
        send(ws, "observation", {**observation(), "states": {**lying, "dtype": "|O"}}, 9)
        assert recv(ws)["seq"] == 9
        send(ws, "hello", {"protocol_version": 2}, 10)
        assert recv(ws)["type"] == "error"
        send(ws, "action", {}, 11)
        assert recv(ws)["type"] == "error"
        ws.send("a text frame")
        assert recv(ws)["type"] == "error"
        send(ws, "observation", observation(), 12)
        reply = recv(ws)
    assert reply["seq"] == 12
    assert action(reply)[0] == 0


def test_an_oversized_frame_closes_that_connection_only() -> None:
    limits = ServeLimits(max_request_bytes=64 << 10)
    with make_server(limits=limits) as running, connect(running.url) as big, connect(running.url) as other:
        big.send(b"\0" * (128 << 10))
        with pytest.raises(ConnectionClosed):
            big.recv(timeout=10)
        send(other, "observation", observation(), 1)
        assert action(recv(other))[0] == 0


def test_images_the_policy_does_not_read_are_not_decoded() -> None:
    with make_server(Echo(observation=["joint_state"])) as running, connect(running.url) as ws:
        send(ws, "hello", {"protocol_version": 1}, 1)
        assert recv(ws)["payload"]["observation_params"] == {"send_state": True}
        garbage = {"__image__": True, "format": "png", "data": b"not a png", "shape": [16, 16, 3]}
        send(ws, "observation", {**observation(), "images": {"agentview": garbage}}, 2)
        row = action(recv(ws))
    assert row[3] == 0
    assert row[4] == 0


def test_health_config_and_the_connection_limit() -> None:
    with make_server(limits=ServeLimits(max_clients=1)) as running:
        base = f"http://{running.host}:{running.port}"
        with urllib.request.urlopen(f"{base}/health", timeout=5) as reply:
            assert json.loads(reply.read()) == {"status": "ok"}
        with urllib.request.urlopen(f"{base}/config", timeout=5) as reply:
            assert json.loads(reply.read())["config"] == {"max_batch_size": 1, "max_wait_time": 0.002}
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"{base}/config?max_batch_size=8", timeout=5)
        assert refused.value.code == 422
        refused.value.close()
        with connect(running.url), connect(running.url), pytest.raises(InvalidStatus) as busy:
            connect(running.url, open_timeout=5)
        assert busy.value.response.status_code == 503


def test_an_api_key_is_required_when_set() -> None:
    with make_server(api_key="s3cret") as running:
        with pytest.raises(InvalidStatus) as refused:
            connect(running.url, open_timeout=5)
        assert refused.value.response.status_code == 401
        with connect(running.url, additional_headers={"Authorization": "Api-Key s3cret"}) as ws:
            send(ws, "observation", observation(), 1)
            assert action(recv(ws)) is not None


def test_rows_anchored_on_privileged_state_cannot_be_served() -> None:
    with pytest.raises(ROSConfigError, match="eef_pos"):
        make_server(Delta())


class Gated(Echo):
    """Its first chunk waits until ``release`` is set."""

    release = threading.Event()
    started = threading.Event()

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        if self.chunks == 0:
            self.started.set()
            assert self.release.wait(10)
        return super()._chunk_impl(request)


@pytest.mark.parametrize("mode", ["sync", "live"])
def test_an_overtaken_observation_is_answered_superseded_in_sync_mode_and_dropped_in_live(mode: str) -> None:
    Gated.release.clear()
    Gated.started.clear()
    skill = Gated()
    with make_server(skill) as running, connect(running.url) as ws:
        send(ws, "episode_start", {"task": {"episode_idx": 0}, "mode": mode}, 1)
        send(ws, "observation", observation(), 2)
        assert Gated.started.wait(10)  # the worker holds the first one
        send(ws, "observation", observation(), 3)
        send(ws, "observation", observation(), 4)  # overtakes 3, still queued
        if mode == "sync":
            superseded = recv(ws)
            assert superseded["seq"] == 3
            assert superseded["payload"]["error"] == "observation_failed: superseded"
        deadline = time.monotonic() + 10
        while running.service.stats.superseded < 1 and time.monotonic() < deadline:  # 4 queued behind the first
            time.sleep(0.005)
        Gated.release.set()
        answered = [recv(ws), recv(ws)]
    assert [reply["seq"] for reply in answered] == [2, 4]
    assert [reply["type"] for reply in answered] == ["action", "action"]


def test_the_cli_offers_every_profile_and_only_with_vla_eval() -> None:
    assert sorted(VLA_EVAL_PROFILES) == sorted(PROFILES)
    result = CliRunner().invoke(
        cli, ["serve", "--protocol", "openpi", "--skill", "zero", "--vla-eval-profile", "plain"]
    )
    assert result.exit_code == EXIT_CONFIG, result.output
    assert "--vla-eval-profile" in result.output


def drain(ws: ClientConnection) -> None:
    """Read until the connection ends (raises ``ConnectionClosed``)."""
    while True:
        ws.recv(timeout=10)


def test_a_client_that_never_reads_its_replies_is_closed(server: VlaEvalServer) -> None:
    raw = socket.create_connection((server.host, server.port))
    raw.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    message = packb(
        {"type": "observation", "payload": {"states": np.zeros(8)}, "seq": 1, "timestamp": 0.0}, dialect="vla_eval"
    )
    with connect(server.url, sock=raw, max_queue=None) as ws:
        try:
            for _ in range(20_000):  # the server reads on; its replies back up
                ws.send(message)
        except ConnectionClosed:
            pass
        with pytest.raises(ConnectionClosed) as closed:
            drain(ws)
    assert closed.value.rcvd is not None
    assert closed.value.rcvd.code == 1008


def test_rows_limits_the_rows_used_of_each_chunk() -> None:
    with make_server(rows=2) as running, connect(running.url) as ws:
        counts = []
        for seq in range(1, 6):
            send(ws, "observation", observation(), seq)
            counts.append(action(recv(ws))[6])
    assert counts == [1, 1, 2, 2, 3]
