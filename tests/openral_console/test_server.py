"""The console's server on a real port: what a page receives, what its buttons do, who is refused."""

from __future__ import annotations

import asyncio
import io
import json
import logging
import socket
import threading
from collections.abc import Awaitable, Callable, Iterator
from typing import Any

import aiohttp
import pytest

from openral_console.feed import unpack_thumbnail
from openral_console.observer import ConsoleObserver
from openral_console.params import ConsoleParams
from openral_core import JointState, ObserverContext, ROSConfigError, TickResult, WorldState
from openral_observability.observer import Thumbnail

_TIMEOUT = aiohttp.ClientTimeout(total=10)
CONTEXT = ObserverContext(robot_id="so101_follower", rate_hz=30.0)
CONSOLE_OPTION = ObserverContext(robot_id="so101_follower", rate_hz=30.0, option="--console")
"""The context of an entry ``--console`` stands for."""


@pytest.fixture
def console() -> Iterator[Callable[..., ConsoleObserver]]:
    """Start consoles on free ports (stderr captured); every one is closed afterwards."""
    made: list[ConsoleObserver] = []

    def start(**params: Any) -> ConsoleObserver:
        observer = ConsoleObserver(ConsoleParams(**{"port": 0, "update_hz": 50, "status_hz": 30, **params}),
                                   announce=io.StringIO())  # fmt: skip
        made.append(observer)
        observer.start()
        return observer

    yield start
    for observer in made:
        observer.close()


def run(body: Callable[[aiohttp.ClientSession], Awaitable[Any]]) -> Any:
    async def main() -> Any:
        async with aiohttp.ClientSession(timeout=_TIMEOUT) as session:
            return await body(session)

    return asyncio.run(main())


def base(observer: ConsoleObserver) -> str:
    return f"http://127.0.0.1:{observer.port}"


def tick(idx: int, sent: list[float] | None = None) -> tuple[TickResult, WorldState]:
    joints = JointState(names=["a", "b"], positions=[0.1 * idx, -0.2], stamp_ns=idx)
    return TickResult(tick_idx=idx, sent_action=sent, action_applied=sent is not None), WorldState(
        stamp_ns=idx, joint_state=joints
    )


async def next_of(ws: aiohttp.ClientWebSocketResponse, kind: str, where: Callable[[Any], bool] = lambda _: True) -> Any:
    """The next message of type ``kind`` (a dict) or, for ``"frame"``, the next binary frame, that matches ``where``."""
    while True:
        message = await ws.receive(timeout=10)
        if message.type is aiohttp.WSMsgType.BINARY and kind == "frame":
            frame = unpack_thumbnail(message.data)
            if where(frame):
                return frame
        elif message.type is aiohttp.WSMsgType.TEXT:
            data = json.loads(message.data)
            if data["type"] == kind and where(data):
                return data
        elif message.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING):
            raise AssertionError(f"socket closed while waiting for {kind}")


def test_building_opens_nothing_and_start_binds_a_free_port_and_prints_the_url() -> None:
    out = io.StringIO()
    observer = ConsoleObserver.from_config({"port": 0}, CONTEXT)
    assert observer.port is None
    assert observer.url is None
    observer._announce = out
    try:
        observer.start()
        observer.start()  # idempotent
        assert observer.port
        assert observer.port > 0
        assert observer.token is None
        assert observer.url == f"http://127.0.0.1:{observer.port}/"
        assert out.getvalue() == f"console: {observer.url}\n"
    finally:
        observer.close()


def test_a_wrong_parameter_is_named_with_the_allowed_keys() -> None:
    with pytest.raises(ROSConfigError, match="--console") as error:
        ConsoleObserver.from_config({"prot": 80}, CONSOLE_OPTION)
    assert "port" in str(error.value)


def test_the_page_is_served_whole_and_offline_with_a_strict_policy(console) -> None:
    observer = console()

    async def body(session: aiohttp.ClientSession) -> None:
        async with session.get(base(observer) + "/") as response:
            assert response.status == 200
            html = await response.text()
            policy = response.headers["Content-Security-Policy"]
            assert response.headers["X-Frame-Options"] == "DENY"
            assert response.headers["Referrer-Policy"] == "no-referrer"
        assert "new WebSocket" in html
        assert "<canvas" not in html.split("<script>")[0]
        assert "http://" not in html
        assert "https://" not in html
        assert "default-src 'none'" in policy
        assert "'sha256-" in policy
        assert "unsafe-inline" not in policy

    run(body)


def test_a_page_gets_the_ticks_joints_health_and_thumbnails(console) -> None:
    observer = console()
    observer.set_status(lambda: {"skill_id": "hello", "live": {"recent_rate_hz": 30.0, "odd": float("nan")}})
    jpeg = b"\xff\xd8fake-jpeg\xff\xd9"

    async def body(session: aiohttp.ClientSession) -> None:
        async with session.ws_connect(base(observer) + "/ws") as ws:
            hello = await next_of(ws, "hello")
            assert hello["controls"] == []
            for i in range(3):
                observer.on_tick(*tick(i, sent=[0.5, -0.5]))
            observer.on_thumbnail(Thumbnail("front", 7, 2, 1, jpeg))
            state = await next_of(ws, "state", lambda s: s["ticks"] == 3 and s["cameras"] == ["front"])
            assert state["sample"]["names"] == ["a", "b"]
            assert state["sample"]["measured"] == pytest.approx([0.2, -0.2])
            assert state["sample"]["commanded"] == [0.5, -0.5]
            assert state["status"]["skill_id"] == "hello"
            assert state["status"]["live"]["odd"] is None  # NaN is not JSON
            header, data = await next_of(ws, "frame")
            assert header == {"sensor_id": "front", "stamp_ns": 7, "width": 2, "height": 1}
            assert data == jpeg
            observer.on_thumbnail(Thumbnail("front", 8, 2, 1, jpeg + b"2"))
            header, data = await next_of(ws, "frame")
            assert header["stamp_ns"] == 8
            assert data == jpeg + b"2"
        async with session.get(base(observer) + "/api/camera/front") as response:
            assert response.status == 200
            assert response.content_type == "image/jpeg"
            assert await response.read() == jpeg + b"2"
        async with session.get(base(observer) + "/api/camera/back") as response:
            assert response.status == 404
        async with session.get(base(observer) + "/api/status") as response:
            status = await response.json()
            assert status["ticks"] == 3
            assert status["status"]["skill_id"] == "hello"

    run(body)


def test_a_page_that_connects_later_gets_the_recent_joint_samples(console) -> None:
    observer = console()

    async def body(session: aiohttp.ClientSession) -> None:
        async with session.ws_connect(base(observer) + "/ws") as first:
            for i in range(5):
                observer.on_tick(*tick(i))
                await next_of(first, "state", lambda s, i=i: s["sample"] is not None and s["sample"]["tick_idx"] == i)
            async with session.ws_connect(base(observer) + "/ws") as second:
                hello = await next_of(second, "hello")
                assert [s["tick_idx"] for s in hello["history"]] == [0, 1, 2, 3, 4]

    run(body)


def test_buttons_run_their_actions_and_a_bad_request_gets_an_error_not_a_crash(console) -> None:
    observer = console()
    pressed: list[str] = []
    done = threading.Event()

    def stop() -> None:
        pressed.append("stop")
        done.set()

    def broken() -> None:
        raise RuntimeError("no leader arm")

    observer.register_control("stop", stop)
    observer.register_control("takeover", broken)

    async def body(session: aiohttp.ClientSession) -> None:
        async with session.ws_connect(base(observer) + "/ws") as ws:
            hello = await next_of(ws, "hello")
            assert hello["controls"] == [{"name": "stop", "label": "Stop"}, {"name": "takeover", "label": "Takeover"}]
            await ws.send_str(json.dumps({"type": "control", "name": "stop", "id": 1}))
            result = await next_of(ws, "control_result")
            assert result == {"type": "control_result", "id": 1, "ok": True, "name": "stop"}
            await ws.send_str(json.dumps({"type": "control", "name": "launch", "id": 2}))
            result = await next_of(ws, "control_result")
            assert result["ok"] is False
            assert "registered: stop, takeover" in result["error"]
            await ws.send_str(json.dumps({"type": "control", "name": "takeover", "id": 3}))
            result = await next_of(ws, "control_result")
            assert result["ok"] is False
            assert "no leader arm" in result["error"]
            for bad in ("not json", "[1, 2]", json.dumps({"type": "dance"}), json.dumps({"type": "control"})):
                await ws.send_str(bad)
                reply = await ws.receive_json(timeout=10)
                while reply["type"] == "state":
                    reply = await ws.receive_json(timeout=10)
                assert reply["type"] in ("error", "control_result")
                assert reply.get("ok") is not True
            await ws.send_bytes(b"\x00\x01")
            assert (await next_of(ws, "error"))["error"] == "send JSON text messages"
        async with session.post(base(observer) + "/api/control/stop") as response:
            assert response.status == 200
        async with session.post(base(observer) + "/api/control/launch") as response:
            assert response.status == 404
        async with session.post(base(observer) + "/api/control/takeover") as response:
            assert response.status == 500
        async with session.get(base(observer) + "/api/status") as response:
            assert response.status == 200  # still serving

    run(body)
    assert done.is_set()
    assert pressed == ["stop", "stop"]
    assert observer._server is not None
    assert observer._server.control_errors == 2


async def _close_code(ws: aiohttp.ClientWebSocketResponse) -> int | None:
    """Read until the server closes the socket; the close code it sent."""
    while True:
        message = await ws.receive(timeout=10)
        if message.type is aiohttp.WSMsgType.CLOSE:
            return int(message.data)
        if message.type in (aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.CLOSING, aiohttp.WSMsgType.ERROR):
            return ws.close_code


def test_garbage_from_a_page_gets_an_error_or_a_quiet_close_never_a_traceback(console, caplog, capfd) -> None:
    observer = console()
    pressed: list[int] = []
    observer.register_control("stop", lambda: pressed.append(1))
    server = observer._server
    assert server is not None

    async def press_stop(session: aiohttp.ClientSession, request_id: int) -> None:
        async with session.ws_connect(base(observer) + "/ws") as ws:
            await next_of(ws, "hello")
            await ws.send_str(json.dumps({"type": "control", "name": "stop", "id": request_id}))
            assert (await next_of(ws, "control_result"))["ok"] is True

    async def body(session: aiohttp.ClientSession) -> None:
        async with session.ws_connect(base(observer) + "/ws") as ws:
            await next_of(ws, "hello")
            await ws.send_str("[" * 3000)  # inside the size limit, deeper than the JSON parser goes
            assert "nested too deeply" in (await next_of(ws, "error"))["error"]
            await ws.send_str(json.dumps({"type": "control", "name": "stop", "id": 1}))  # the page goes on working
            assert (await next_of(ws, "control_result"))["ok"] is True
        async with session.ws_connect(base(observer) + "/ws") as ws:
            await next_of(ws, "hello")
            await ws.send_str("x" * 70_000)  # over the size limit: the console closes the socket
            assert await _close_code(ws) == aiohttp.WSCloseCode.MESSAGE_TOO_BIG
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 10
        while server._pages:  # both pages' handlers have returned (or raised)
            assert loop.time() < deadline, "a page's handler did not finish"
            await asyncio.sleep(0.01)
        await press_stop(session, 2)  # a new page is served as before

    run(body)
    assert pressed == [1, 1]
    errors = [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]
    assert errors == [], [r.getMessage() for r in errors]
    assert "Traceback" not in capfd.readouterr().err


def test_a_non_loopback_bind_refuses_everything_without_the_token(console) -> None:
    observer = console(host="0.0.0.0")
    assert observer.token is not None
    assert observer.url is not None
    assert observer.url.endswith(f":{observer.port}/?token={observer.token}")
    pressed: list[str] = []
    observer.register_control("stop", lambda: pressed.append("stop"))
    observer.register_control("next", lambda: pressed.append("next"))
    url = base(observer)

    async def body(session: aiohttp.ClientSession) -> None:
        for suffix, status in (("", 401), ("?token=wrong", 403)):
            for path in ("/", "/api/status", "/api/camera/front"):
                async with session.get(url + path + suffix) as response:
                    assert response.status == status, path
            for name in ("stop", "next", "nope"):
                async with session.post(url + f"/api/control/{name}" + suffix) as response:
                    assert response.status == status, name
            with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
                await session.ws_connect(url + "/ws" + suffix)
            assert refused.value.status == status
        token = f"?token={observer.token}"
        async with session.get(url + "/" + token) as response:
            assert response.status == 200
        headers = {"Authorization": f"Bearer {observer.token}"}
        async with session.post(url + "/api/control/next", headers=headers) as response:
            assert response.status == 200
        async with session.ws_connect(url + "/ws" + token) as ws:
            await next_of(ws, "hello")
            await ws.send_str(json.dumps({"type": "control", "name": "stop", "id": 1}))
            assert (await next_of(ws, "control_result"))["ok"] is True

    run(body)
    assert pressed == ["next", "stop"]


def test_on_loopback_no_token_is_needed_but_other_sites_and_rebinding_names_are_refused(console) -> None:
    observer = console()
    pressed: list[str] = []
    observer.register_control("stop", lambda: pressed.append("stop"))
    url = base(observer)

    async def body(session: aiohttp.ClientSession) -> None:
        evil = {"Origin": "http://evil.example"}
        async with session.post(url + "/api/control/stop", headers=evil) as response:
            assert response.status == 403
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await session.ws_connect(url + "/ws", headers=evil)
        assert refused.value.status == 403
        async with session.get(url + "/", headers={"Host": f"evil.example:{observer.port}"}) as response:
            assert response.status == 403
        async with session.post(url + "/api/control/stop", headers={"Origin": url}) as response:
            assert response.status == 200

    run(body)
    assert pressed == ["stop"]


def test_one_page_too_many_is_refused(console) -> None:
    observer = console(max_clients=1)

    async def body(session: aiohttp.ClientSession) -> None:
        async with session.ws_connect(base(observer) + "/ws") as ws:
            await next_of(ws, "hello")
            with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
                await session.ws_connect(base(observer) + "/ws")
            assert refused.value.status == 503

    run(body)


def test_close_tells_open_pages_and_releases_the_port(console) -> None:
    observer = console()
    port = observer.port
    assert port is not None

    async def body(session: aiohttp.ClientSession) -> None:
        async with session.ws_connect(base(observer) + "/ws") as ws:
            await next_of(ws, "hello")
            await asyncio.get_running_loop().run_in_executor(None, observer.close)
            closed = await next_of(ws, "closed")
            assert closed["reason"] == "the run ended"

    run(body)
    observer.close()  # idempotent
    with socket.create_server(("127.0.0.1", port)):  # the port is free again
        pass
    observer.start()  # closed for good: a late start opens nothing
    assert observer.port == port


def test_a_port_in_use_is_a_configuration_error_naming_the_option() -> None:
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        observer = ConsoleObserver.from_config({"port": port}, CONSOLE_OPTION)
        with pytest.raises(ROSConfigError, match=r"--console.*choose another port"):
            observer.start()
        observer.close()


def test_closing_a_console_that_never_started_is_fine() -> None:
    observer = ConsoleObserver()
    observer.close()
    observer.close()
    assert observer.port is None
