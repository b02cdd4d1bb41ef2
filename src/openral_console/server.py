"""``ConsoleServer``: the console's HTTP and WebSocket server, on its own thread and asyncio loop.

Routes (every one behind :mod:`openral_console.auth`):

- ``GET /``: the page (:mod:`openral_console.page`).
- ``GET /ws``: the page's WebSocket. The server sends a ``hello`` (the buttons, the recent joint
  samples), then a ``state`` message ``update_hz`` times a second, and each camera's newer
  thumbnail (binary, :func:`~openral_console.feed.pack_thumbnail`) at most ``image_hz`` times a
  second; the page sends ``{"type": "control", "name": ..., "id": ...}`` and is answered with a
  ``control_result``.
- ``GET /api/status``: the ``state`` message as JSON, freshly computed.
- ``GET /api/camera/{sensor_id}``: a camera's newest thumbnail (JPEG).
- ``POST /api/control/{name}``: press a button (200, 404 unknown, 500 when its action failed).

One producer task renders the state once per period for every page; each page has its own
sender, which always sends the newest state and skips what it could not send in time, so a slow
page never queues and never slows another. The loop sleeps unless a page is open.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import threading
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

import structlog

from openral_console.auth import TOKEN_PARAM, foreign_origin, host_header_ok, token_status
from openral_console.feed import ConsoleFeed, Control, dumps, pack_thumbnail
from openral_console.page import SECURITY_HEADERS, load_page
from openral_console.params import ConsoleParams
from openral_core import ROSConfigError, ROSDependencyMissing
from openral_observability.observer import Thumbnail


def _missing() -> ROSDependencyMissing:
    return ROSDependencyMissing("aiohttp", extra="console", needed_for="the web console (--console)")


try:
    from aiohttp import WSMsgType, web
except ImportError as exc:  # pragma: no cover - exercised with the extra missing
    raise _missing() from exc


def check_installed() -> None:
    """Refuse now what :meth:`ConsoleServer.start` would: a console built without aiohttp names the extra.

    Raises:
        ROSDependencyMissing: aiohttp cannot be imported (the ``console`` extra).
    """
    try:
        import aiohttp  # noqa: F401, PLC0415 - the check itself: the 'console' extra
    except ImportError as exc:
        raise _missing() from exc


_log = structlog.get_logger(__name__)

_START_TIMEOUT_S = 10.0
_CLOSE_TIMEOUT_S = 5.0
_MAX_MESSAGE = 4096
"""Largest message a page may send (a control request is a few dozen bytes)."""

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class _Page:
    """One open page: its socket, a lock so its sends do not interleave, and what it was sent."""

    def __init__(self, ws: web.WebSocketResponse) -> None:
        self.ws = ws
        self.lock = asyncio.Lock()
        self.sent: dict[str, Thumbnail] = {}
        self.image_due: dict[str, float] = {}


class ConsoleServer:
    """Serves ``feed`` to browsers while started.

    Args:
        feed: What the pages show and the buttons they have.
        params: Host, port, rates, limits.
        token: Required on every request when not ``None`` (a non-loopback bind).
        option: The command-line option or field that configured it, for errors.
    """

    def __init__(self, feed: ConsoleFeed, params: ConsoleParams, *, token: str | None, option: str) -> None:
        self._feed = feed
        self._params = params
        self._token = token
        self._option = option
        self._page = load_page()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._producer: asyncio.Task[None] | None = None
        self._pages: set[_Page] = set()
        self._changed: asyncio.Condition | None = None
        self._version = 0
        self._state_text = ""
        self._packed: dict[str, tuple[Thumbnail, bytes]] = {}
        self._status: Mapping[str, Any] | None = None
        self._next_status = 0.0
        self._history: deque[dict[str, Any]] = deque(maxlen=max(1, params.history))
        self._last_sample_tick: tuple[int, int] | None = None
        self._closed = False
        self.port: int | None = None
        """The bound port (the real one when 0 was asked), ``None`` until started."""
        self.control_errors = 0
        """Button presses whose action raised."""

    # -- lifecycle (caller's thread) --------------------------------------------------------

    def start(self) -> None:
        """Bind the port and serve on a new thread. Idempotent.

        Raises:
            ROSConfigError: The address cannot be bound.
        """
        if self._thread is not None or self._closed:
            return
        sock = self._bind()
        self.port = int(sock.getsockname()[1])
        loop = asyncio.new_event_loop()
        thread = threading.Thread(target=self._run_loop, args=(loop,), name="openral-console", daemon=True)
        thread.start()
        self._loop, self._thread = loop, thread
        try:
            asyncio.run_coroutine_threadsafe(self._serve(sock), loop).result(_START_TIMEOUT_S)
        except BaseException:
            sock.close()
            self.close()
            raise

    def close(self) -> None:
        """Tell open pages the run ended, stop serving and release the port. Idempotent."""
        if self._closed:
            return
        self._closed = True
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        try:
            asyncio.run_coroutine_threadsafe(self._shutdown(), loop).result(_CLOSE_TIMEOUT_S)
        except Exception as exc:  # a page that would not close must not keep the port
            _log.warning("console did not shut down cleanly", error=repr(exc))
        loop.call_soon_threadsafe(loop.stop)
        thread.join(_CLOSE_TIMEOUT_S)
        if thread.is_alive():
            _log.error("console thread did not stop in time")

    def _bind(self) -> socket.socket:
        host, port = self._params.host, self._params.port
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
            family, kind, proto, _, address = infos[0]
            sock = socket.socket(family, kind, proto)
        except OSError as exc:
            raise ROSConfigError(
                f"cannot serve the console on {host}:{port}: {exc}",
                field=self._option,
                hint="give a host name or address of this machine",
            ) from exc
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(address)
            sock.listen(64)
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise ROSConfigError(
                f"cannot serve the console on {host}:{port}: {exc.strerror or exc}",
                field=self._option,
                hint="choose another port, or 0 for any free one",
            ) from exc
        return sock

    @staticmethod
    def _run_loop(loop: asyncio.AbstractEventLoop) -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_forever()
        finally:
            with contextlib.suppress(Exception):
                loop.run_until_complete(loop.shutdown_default_executor())
            loop.close()

    # -- the loop's side --------------------------------------------------------------------

    async def _serve(self, sock: socket.socket) -> None:
        app = web.Application(middlewares=[self._guard], client_max_size=_MAX_MESSAGE)
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/api/status", self._status_json)
        app.router.add_get("/api/camera/{sensor_id}", self._camera)
        app.router.add_post("/api/control/{name}", self._control_post)
        app.on_response_prepare.append(self._headers)
        app.on_shutdown.append(self._close_pages)
        runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
        await runner.setup()
        self._runner = runner
        await web.SockSite(runner, sock).start()
        self._changed = asyncio.Condition()
        self._producer = asyncio.create_task(self._produce())

    async def _shutdown(self) -> None:
        if self._producer is not None:
            self._producer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._producer
        if self._runner is not None:
            await self._runner.cleanup()  # on_shutdown closes the pages first

    async def _close_pages(self, _app: web.Application) -> None:
        async def bye(page: _Page) -> None:
            with contextlib.suppress(Exception):
                async with page.lock:
                    await page.ws.send_str(dumps({"type": "closed", "reason": "the run ended"}))
                await page.ws.close(code=1001, message=b"the run ended")

        await asyncio.gather(*(bye(page) for page in list(self._pages)))

    @web.middleware
    async def _guard(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Refuse what may not reach the console: no token or a wrong one, another site's page, a foreign Host."""
        if self._token is None and not host_header_ok(request.headers.get("Host")):
            return _error(403, "the Host header must name this machine (loopback)")
        refused = token_status(self._token, request.query.get(TOKEN_PARAM), request.headers.get("Authorization"))
        if refused is not None:
            what = "a token is required" if refused == 401 else "wrong token"
            return _error(refused, f"{what}: open the URL the console printed at start")
        if (request.method != "GET" or request.path == "/ws") and foreign_origin(
            request.headers.get("Origin"), request.host
        ):
            return _error(403, "requests from another site's page are refused")
        return await handler(request)

    @staticmethod
    async def _headers(request: web.Request, response: web.StreamResponse) -> None:
        for name, value in SECURITY_HEADERS.items():
            response.headers.setdefault(name, value)

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.Response(
            body=self._page.html,
            content_type="text/html",
            charset="utf-8",
            headers={"Content-Security-Policy": self._page.csp},
        )

    async def _status_json(self, request: web.Request) -> web.StreamResponse:
        return web.Response(text=dumps(self._feed.state(self._read_status())), content_type="application/json")

    async def _camera(self, request: web.Request) -> web.StreamResponse:
        thumb = self._feed.thumbnails().get(request.match_info["sensor_id"])
        if thumb is None:
            return _error(404, "no thumbnail of that camera yet")
        return web.Response(body=thumb.jpeg, content_type="image/jpeg")

    async def _control_post(self, request: web.Request) -> web.StreamResponse:
        result = await self._press(request.match_info["name"], peer=request.remote)
        status = 200 if result["ok"] else (404 if result.get("unknown") else 500)
        return web.Response(text=dumps(result), status=status, content_type="application/json")

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        if len(self._pages) >= self._params.max_clients:
            return _error(503, f"{self._params.max_clients} pages are open already")
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=_MAX_MESSAGE, compress=False, timeout=2.0)
        await ws.prepare(request)
        page = _Page(ws)
        self._pages.add(page)
        sender = asyncio.create_task(self._send(page))
        try:
            async for message in ws:
                if message.type is WSMsgType.ERROR:  # too long or not a WebSocket frame: aiohttp closes the socket
                    _log.info(
                        "console page closed: it sent what the console does not take",
                        peer=request.remote,
                        reason=str(message.data),
                    )
                    break
                if message.type is WSMsgType.TEXT:
                    reply = await self._on_text(message.data, peer=request.remote)
                else:
                    reply = {"type": "error", "error": "send JSON text messages"}
                if not await _reply(page, reply):
                    break
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                await sender
            self._pages.discard(page)
        return ws

    async def _on_text(self, text: str, *, peer: str | None) -> dict[str, Any]:
        """Answer one message of a page; a malformed one gets an error, never an exception."""
        try:
            message = _json_object(text)
        except ValueError as exc:
            return {"type": "error", "error": f"not a JSON object: {exc}"}
        if message.get("type") != "control":
            return {"type": "error", "error": f"unknown message type {message.get('type')!r}; known: control"}
        name = message.get("name")
        result = await self._press(name if isinstance(name, str) else "", peer=peer)
        request_id = message.get("id")
        return {"type": "control_result", "id": request_id if isinstance(request_id, int | str) else None, **result}

    async def _press(self, name: str, *, peer: str | None) -> dict[str, Any]:
        """Run control ``name``'s action off the loop; what happened, as the page is told."""
        control: Control | None = self._feed.controls.get(name)
        if control is None:
            known = ", ".join(self._feed.controls.names()) or "none"
            return {"ok": False, "unknown": True, "name": name[:64], "error": f"unknown control; registered: {known}"}
        _log.info("console control", control=name, peer=peer)
        try:
            await asyncio.get_running_loop().run_in_executor(None, control.action)
        except Exception as exc:  # a failing action is reported to the page, never fatal to the server
            self.control_errors += 1
            _log.error("console control failed", control=name, error=repr(exc))
            return {"ok": False, "name": name, "error": f"{type(exc).__name__}: {exc}"}
        return {"ok": True, "name": name}

    def _read_status(self) -> Mapping[str, Any] | None:
        source = self._feed.status
        if source is None:
            return None
        try:
            return source()
        except Exception as exc:  # a status that cannot be read is shown as such
            return {"error": f"{type(exc).__name__}: {exc}"}

    async def _produce(self) -> None:
        """Once per period while a page is open: the health (at its own rate), the state, new thumbnails."""
        assert self._changed is not None
        loop = asyncio.get_running_loop()
        period = 1.0 / self._params.update_hz
        status_period = 1.0 / self._params.status_hz
        due = loop.time()
        while True:
            due += period
            now = loop.time()
            if due < now:
                due = now + period  # fell behind (a stalled process): the next period, never a burst
            await asyncio.sleep(due - now)
            if not self._pages:
                continue
            if loop.time() >= self._next_status:
                self._status = self._read_status()
                self._next_status = loop.time() + status_period
            state = self._feed.state(self._status)
            self._remember(state.get("sample"))
            for sensor_id, thumb in self._feed.thumbnails().items():
                packed = self._packed.get(sensor_id)
                if packed is None or packed[0] is not thumb:
                    self._packed[sensor_id] = (thumb, pack_thumbnail(thumb))
            self._state_text = dumps(state)
            self._version += 1
            async with self._changed:
                self._changed.notify_all()

    def _remember(self, sample: dict[str, Any] | None) -> None:
        if sample is None:
            return
        key = (self._feed.ticks_seen, sample["tick_idx"])
        if key != self._last_sample_tick:
            self._last_sample_tick = key
            self._history.append(sample)

    async def _send(self, page: _Page) -> None:
        """One page's sender: the hello, then the newest state and thumbnails whenever there is a newer one."""
        assert self._changed is not None
        changed = self._changed
        hello = {
            "type": "hello",
            "update_hz": self._params.update_hz,
            "controls": self._feed.controls.describe(),
            "history": list(self._history) if self._params.history else [],
        }
        async with page.lock:
            await page.ws.send_str(dumps(hello))
        loop = asyncio.get_running_loop()
        image_period = 1.0 / self._params.image_hz
        seen = self._version if not self._state_text else -1  # nothing rendered yet: wait for the first state
        while not page.ws.closed:
            async with changed:
                while self._version == seen:
                    await changed.wait()
            seen = self._version
            async with page.lock:
                await page.ws.send_str(self._state_text)
                now = loop.time()
                for sensor_id, (thumb, data) in list(self._packed.items()):
                    if page.sent.get(sensor_id) is thumb or now < page.image_due.get(sensor_id, 0.0):
                        continue
                    page.sent[sensor_id] = thumb
                    page.image_due[sensor_id] = now + image_period * 0.9  # slack: a period is a few updates
                    await page.ws.send_bytes(data)


async def _reply(page: _Page, reply: dict[str, Any]) -> bool:
    """Send ``reply`` to ``page``; ``False`` when its socket is closing (the page went away: nothing to tell)."""
    async with page.lock:
        if page.ws.closed:
            return False
        try:
            await page.ws.send_str(dumps(reply))
        except ConnectionError:
            return False
    return True


def _json_object(text: str) -> dict[str, Any]:
    """The JSON object ``text`` holds.

    Raises:
        ValueError: Not JSON (nested too deeply included), or not an object.
    """
    try:
        value = json.loads(text)
    except RecursionError:  # a few thousand brackets fit in a message
        raise ValueError("nested too deeply") from None
    if not isinstance(value, dict):
        raise ValueError(f"got {type(value).__name__}")
    return value


def _error(status: int, message: str) -> web.Response:
    return web.Response(text=dumps({"ok": False, "error": message}), status=status, content_type="application/json")
