"""Hostile openpi clients: refused unread, a robot under way keeps being served, and the memory stays bounded."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import msgpack
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, ConnectionClosedError, InvalidStatus
from websockets.sync.client import ClientConnection, connect

from openral_remote.admission import ServeLimits
from openral_remote.msgpack_numpy import packb, unpackb
from openral_remote.openpi_profiles import OpenpiProfile
from openral_remote.openpi_server import OpenpiServer
from openral_remote.testing import ChunkSkill, chunk_meta, wait_for

pytestmark = pytest.mark.timeout(180)

NAMES = ["a0", "a1"]
LIMITS = ServeLimits(max_request_bytes=1 << 20, max_clients=4, max_pending=8, max_image_pixels=320 * 240)


@pytest.fixture
def server() -> Iterator[OpenpiServer]:
    skill = ChunkSkill(NAMES, observation=())
    served = OpenpiServer(
        skill,
        meta=chunk_meta(skill, rate_hz=30.0, model_hash="m" * 64),
        profile=OpenpiProfile("openral", image_size=None, state_names=NAMES),
        port=0,
        limits=LIMITS,
    )
    with served:
        yield served


def _connect(server: OpenpiServer) -> ClientConnection:
    return connect(server.url, compression=None, max_size=None, open_timeout=20)


def _obs(q: float) -> bytes:
    return packb({"observation/state": np.array([q, 0.0]), "prompt": "reach"})


def _infer(ws: ClientConnection, q: float) -> np.ndarray:
    ws.send(_obs(q))
    reply = ws.recv(timeout=20)
    assert isinstance(reply, bytes), reply
    actions = unpackb(reply)["actions"]
    assert isinstance(actions, np.ndarray)
    return actions


def _array(data: bytes, dtype: str, shape: list[int]) -> dict[bytes, Any]:
    return {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}


def _raw(obs: dict[str, Any]) -> bytes:
    return msgpack.packb(obs)  # type: ignore[no-any-return]


HOSTILE: dict[str, tuple[bytes | str, str]] = {
    "garbage msgpack": (b"\xc1\xff garbage", "not a msgpack message"),
    "not a map": (msgpack.packb([1, 2, 3]), "a map with text keys"),
    "lying shape": (_raw({"observation/state": _array(b"\0" * 16, "<f8", [1000, 1000])}), "announced as shape"),
    "object dtype": (_raw({"observation/state": _array(b"\0" * 16, "|O", [2])}), "refused"),
    "pickled scalar": (_raw({"observation/state": {b"__npgeneric__": True, b"data": b"x", b"dtype": "|O"}}), "refused"),
    "too many dimensions": (_raw({"observation/state": _array(b"", "<f8", [0] * 40)}), "bad shape"),
    "wrong state size": (packb({"observation/state": np.zeros(7)}), "shape (7,)"),
    "unknown key": (packb({"observation/state": np.zeros(2), "weights": np.zeros(3)}), "unexpected key"),
    "huge image": (
        packb({"observation/state": np.zeros(2), "observation/images/front": np.zeros((300, 400, 3), np.uint8)}),
        "over the server's",
    ),
    "text frame": ("{}", "binary msgpack frame"),
}


@pytest.mark.parametrize("name", list(HOSTILE))
def test_a_hostile_request_is_refused_and_the_robot_keeps_being_served(server: OpenpiServer, name: str) -> None:
    message, reason = HOSTILE[name]
    with _connect(server) as robot, _connect(server) as attacker:
        robot.recv(timeout=20)
        attacker.recv(timeout=20)
        first = _infer(robot, 0.0)
        attacker.send(message)
        text = attacker.recv(timeout=20)
        assert isinstance(text, str)
        assert reason in text
        with pytest.raises(ConnectionClosedError) as closed:
            attacker.recv(timeout=20)
        assert closed.value.rcvd is not None
        assert closed.value.rcvd.code == 1011
        assert _infer(robot, 0.2)[0, 0] == pytest.approx(first[0, 0] + 0.2)
    assert server.stats.refused == 1
    assert server.stats.errors == 0


def test_an_oversized_frame_closes_its_connection_unread(server: OpenpiServer) -> None:
    with _connect(server) as robot, _connect(server) as attacker:
        robot.recv(timeout=20)
        attacker.recv(timeout=20)
        attacker.send(b"\0" * (2 << 20))  # twice max_request_bytes
        with pytest.raises(ConnectionClosed) as closed:
            attacker.recv(timeout=20)
        assert closed.value.rcvd is not None
        assert closed.value.rcvd.code == 1009
        assert _infer(robot, 0.1).shape == (10, 2)


def _rss_mib() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_a_flood_of_connections_is_refused_while_a_robot_is_served_and_memory_stays_bounded(
    server: OpenpiServer,
) -> None:
    lying = _raw({"observation/state": _array(b"\0" * (900 << 10), "<f8", [2])})  # ~1 MB that lies about its shape
    with _connect(server) as robot:
        robot.recv(timeout=20)
        _infer(robot, 0.0)
        stop = threading.Event()
        outcomes: dict[str, int] = {"refused": 0, "full": 0, "lying": 0}

        def attack() -> None:
            while not stop.is_set():
                try:
                    with _connect(server) as ws:
                        ws.recv(timeout=20)
                        ws.send(lying)
                        text = ws.recv(timeout=20)
                        outcomes["full" if str(text).startswith("full") else "lying"] += 1
                except InvalidStatus:
                    outcomes["refused"] += 1  # over the connection limit: 503 at the upgrade
                except ConnectionClosed:
                    outcomes["lying"] += 1

        attackers = [threading.Thread(target=attack, daemon=True) for _ in range(12)]
        baseline = _rss_mib()
        for thread in attackers:
            thread.start()
        try:
            assert wait_for(lambda: sum(outcomes.values()) > 150, timeout_s=90)
            for i in range(20):  # every request answered, in time, with its own chunk
                assert _infer(robot, 0.01 * i)[0, 0] == pytest.approx(0.01 * i + 0.5)
        finally:
            stop.set()
            for thread in attackers:
                thread.join(timeout=30)
        grown = _rss_mib() - baseline
    assert outcomes["full"] + outcomes["refused"] > 0  # more connections than max_clients were turned away
    assert grown < 60  # hundreds of 1 MB requests and connections leave nothing behind
    assert wait_for(lambda: server.service.clients == 0)  # every episode freed with its connection
