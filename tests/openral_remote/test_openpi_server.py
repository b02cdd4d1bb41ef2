"""openpi's websocket protocol served by openral: metadata first, chunks, errors, keys, TLS, batching, episodes."""

from __future__ import annotations

import contextlib
import ssl
import threading
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, ConnectionClosedError, InvalidHandshake, InvalidStatus
from websockets.sync.client import ClientConnection, connect

from openral_core import JointState, WorldState
from openral_remote.admission import ServeLimits
from openral_remote.config import TlsConfig
from openral_remote.msgpack_numpy import packb, unpackb
from openral_remote.openpi_profiles import OpenpiProfile
from openral_remote.openpi_server import OpenpiServer
from openral_remote.testing import ChunkSkill, chunk_meta, wait_for
from openral_remote.testing_tls import make_ca, make_certificate

pytestmark = pytest.mark.timeout(120)

NAMES = ["a0", "a1"]
Serve = Callable[..., tuple[OpenpiServer, list[ChunkSkill]]]


@pytest.fixture
def serve() -> Iterator[Serve]:
    """``serve(limits=..., api_key=..., tls=..., **skill_kwargs)``: an OpenpiServer of ChunkSkills on a free port."""
    servers: list[OpenpiServer] = []

    def start(
        limits: ServeLimits | None = None, api_key: str | None = None, tls: TlsConfig | None = None, **kwargs: Any
    ) -> tuple[OpenpiServer, list[ChunkSkill]]:
        built: list[ChunkSkill] = []

        def make() -> ChunkSkill:
            built.append(ChunkSkill(NAMES, **kwargs))
            return built[-1]

        skill = make()
        server = OpenpiServer(
            skill,
            meta=chunk_meta(skill, rate_hz=30.0, model_hash="m" * 64),
            profile=OpenpiProfile("openral", image_size=None, state_names=NAMES),
            port=0,
            limits=limits,
            factory=make,
            api_key=api_key,
            tls=tls,
        )
        server.start()
        servers.append(server)
        return server, built

    yield start
    for server in servers:
        server.close()


def _recv(ws: Any) -> Any:
    """The next frame, decoded (a text frame fails the test, quoting it)."""
    reply = ws.recv(timeout=20)
    assert isinstance(reply, bytes), reply
    return unpackb(reply)


def _obs(q: tuple[float, float]) -> bytes:
    return packb({"observation/state": np.asarray(q, dtype=np.float64), "prompt": "reach"})


def _connect(server: OpenpiServer, **kwargs: Any) -> ClientConnection:
    connection: ClientConnection = connect(server.url, compression=None, max_size=None, open_timeout=20, **kwargs)
    return connection


def _infer(ws: ClientConnection, q: tuple[float, float]) -> dict[str, Any]:
    ws.send(_obs(q))
    reply = ws.recv(timeout=20)
    assert isinstance(reply, bytes), reply
    return unpackb(reply)  # type: ignore[no-any-return]


def _healthz(server: OpenpiServer) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=10) as response:
        return str(response.read().decode())


def test_metadata_comes_first_then_each_observation_gets_its_chunk(serve: Serve) -> None:
    server, built = serve(chunk_size=12)
    with _connect(server) as ws:
        meta = _recv(ws)
        assert meta["action_horizon"] == 12
        assert meta["action_dim"] == 2
        assert meta["openral"]["action_names"] == NAMES
        assert meta["openral"]["model_hash"] == "m" * 64
        first = _infer(ws, (0.1, 0.2))
        second = _infer(ws, (0.3, 0.0))
    assert first["actions"].dtype == np.float32
    assert first["actions"].shape == (12, 2)
    np.testing.assert_allclose(first["actions"], built[0].rows(_world((0.1, 0.2))), rtol=1e-6)
    np.testing.assert_allclose(second["actions"][0], [0.8, 0.5], rtol=1e-6)
    assert "prev_total_ms" not in first["server_timing"]
    assert second["server_timing"]["prev_total_ms"] > 0
    assert _healthz(server) == "OK\n"


def _world(q: tuple[float, float]) -> WorldState:
    return WorldState(stamp_ns=1, joint_state=JointState(names=NAMES, positions=list(q)))


def test_healthz_and_other_clients_are_answered_while_an_inference_runs(
    serve: Serve, monkeypatch: pytest.MonkeyPatch
) -> None:
    server, built = serve()
    inferring, release = threading.Event(), threading.Event()
    infer = built[0]._chunks_impl

    def held(requests: Any) -> list[np.ndarray]:
        inferring.set()
        assert release.wait(60), "the test never released the inference"
        return infer(requests)

    monkeypatch.setattr(built[0], "_chunks_impl", held)  # the inference runs until released
    try:
        with _connect(server) as slow:
            slow.recv(timeout=20)
            slow.send(_obs((0.0, 0.0)))
            assert inferring.wait(20)  # the inference is under way, held there
            assert _healthz(server) == "OK\n"  # answered while it is held
            with _connect(server) as other:
                assert _recv(other)["action_horizon"] == 10
            release.set()
            assert _recv(slow)["actions"].shape == (10, 2)
    finally:
        release.set()


def test_an_error_is_a_text_frame_then_1011_and_the_others_keep_being_served(serve: Serve) -> None:
    server, _built = serve()
    with _connect(server) as robot, _connect(server) as bad:
        robot.recv(timeout=20)
        bad.recv(timeout=20)
        _infer(robot, (0.0, 0.0))
        bad.send(packb({"observation/state": np.zeros(3), "prompt": "x"}))  # the robot has two joints
        text = bad.recv(timeout=20)
        assert isinstance(text, str)
        assert text.startswith("refused: ")
        assert "\n" not in text
        with pytest.raises(ConnectionClosedError) as closed:
            bad.recv(timeout=20)
        assert closed.value.rcvd is not None
        assert closed.value.rcvd.code == 1011
        assert _infer(robot, (0.2, 0.0))["actions"][0, 0] == pytest.approx(0.7)
    assert server.stats.refused == 1


def test_an_inference_that_fails_is_reported_to_its_client_alone(serve: Serve) -> None:
    server, built = serve()
    with _connect(server) as robot, _connect(server) as other:
        robot.recv(timeout=20)
        other.recv(timeout=20)
        built[0].delay_s = float("nan")  # time.sleep(nan) raises: the inference fails
        other.send(_obs((0.0, 0.0)))
        text = other.recv(timeout=20)
        assert isinstance(text, str)
        assert "ValueError" in text
        built[0].delay_s = 0.0
        assert _infer(robot, (0.0, 0.0))["actions"].shape == (10, 2)
    assert server.stats.errors == 1


def test_an_api_key_is_required_when_set(serve: Serve) -> None:
    server, _built = serve(api_key="s3cret-key")
    assert _healthz(server) == "OK\n"  # a probe needs no key
    for headers in ({}, {"Authorization": "Api-Key wrong"}, {"Authorization": "s3cret-key"}):
        with pytest.raises(InvalidStatus) as refused:
            _connect(server, additional_headers=headers)
        assert refused.value.response.status_code == 401
    with _connect(server, additional_headers={"Authorization": "Api-Key s3cret-key"}) as ws:
        assert _recv(ws)["action_dim"] == 2
        assert _infer(ws, (0.0, 0.0))["actions"].shape == (10, 2)


def test_tls_serves_wss_and_mutual_tls_needs_a_client_certificate(serve: Serve, tmp_path: Path) -> None:
    ca = make_ca(tmp_path)
    cert = make_certificate(tmp_path, "server", ca)
    robot = make_certificate(tmp_path, "robot", ca)
    server, _built = serve(tls=TlsConfig(ca=str(ca.cert), cert=str(cert.cert), key=str(cert.key), mutual=True))
    assert server.url.startswith("wss://")
    trusting = ssl.create_default_context(cafile=str(ca.cert))
    no_link = (ssl.SSLError, OSError, InvalidHandshake, ConnectionClosed)
    with pytest.raises(no_link), _connect(server, ssl=trusting) as ws:  # no certificate of its own
        ws.recv(timeout=20)
    trusting.load_cert_chain(str(robot.cert), str(robot.key))
    with _connect(server, ssl=trusting) as ws:
        assert _recv(ws)["action_horizon"] == 10
        assert _infer(ws, (0.0, 0.0))["actions"].shape == (10, 2)


def test_concurrent_clients_are_batched_each_getting_its_own_chunk(serve: Serve) -> None:
    server, built = serve(limits=ServeLimits(max_batch=8, max_wait_ms=100), batch=8, delay_s=0.05)
    with contextlib.ExitStack() as stack:
        sockets = [stack.enter_context(_connect(server)) for _ in range(6)]
        for ws in sockets:
            ws.recv(timeout=20)
        results: dict[int, np.ndarray] = {}

        def ask(i: int) -> None:
            for _ in range(3):
                results[i] = _infer(sockets[i], (0.1 * i, 0.0))["actions"]

        threads = [threading.Thread(target=ask, args=(i,)) for i in range(len(sockets))]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
    assert sorted(results) == list(range(6))
    for i, actions in results.items():
        assert actions[0, 0] == pytest.approx(0.1 * i + 0.5)
    assert max(built[0].batch_sizes) > 1
    assert server.stats.largest_batch > 1


def test_each_connection_is_an_episode_freed_when_it_closes(serve: Serve) -> None:
    server, built = serve(latch=True)  # keeps episode state: an instance per client
    with _connect(server) as first:
        first.recv(timeout=20)
        assert _infer(first, (0.1, 0.0))["actions"][0, 0] == pytest.approx(0.6)
        assert _infer(first, (0.4, 0.0))["actions"][0, 0] == pytest.approx(0.6)  # latched on its first observation
        with _connect(server) as second:
            second.recv(timeout=20)
            assert _infer(second, (0.3, 0.0))["actions"][0, 0] == pytest.approx(0.8)  # an episode of its own
            assert server.service.clients == 2
    assert wait_for(lambda: server.service.clients == 0)
    with _connect(server) as again:  # a new connection starts a new episode
        again.recv(timeout=20)
        assert _infer(again, (0.2, 0.0))["actions"][0, 0] == pytest.approx(0.7)
    assert server.stats.resets == 3
    assert len(built) == 2  # the first client's instance was handed on, not rebuilt
