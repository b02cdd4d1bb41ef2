"""``OpenpiServer``: a policy served to openpi's clients (openpi-client's ``WebsocketClientPolicy``).

openpi's protocol is a websocket of msgpack frames (:mod:`openral_remote.msgpack_numpy`, openpi's
dialect): the server sends one metadata frame on connect, then answers each observation dict with
``{"actions": float32 (H, D), "server_timing": {...}}``. ``GET /healthz`` answers ``OK``. An
error is a text frame with a one-line message, then a close with code 1011.

What openral adds behind it:

* Inference never runs in the event loop: each request goes to a
  :class:`~openral_remote.service.PolicyService` (the Zenoh server's admission, fair queue and
  batching) and its answer comes back to the loop with ``call_soon_threadsafe``, so one client's
  inference neither blocks another's socket nor ``/healthz``.
* One connection is one client episode (the protocol has no reset): reset on connect, freed on close.
* Hostile input is bounded: a frame's size (``max_request_bytes``), its nesting and entries, every
  array's dimensions, elements, dtype (numbers only) and byte count; nothing is unpickled. A request
  that does not fit the profile (:mod:`openral_remote.openpi_profiles`) or the policy's inputs is
  refused before its arrays are decoded. Connections beyond twice ``max_clients`` are refused at
  the upgrade (503).
* An API key (``Authorization: Api-Key <key>``, compared in constant time; 401 otherwise) and TLS
  (``wss://``, with mutual TLS) when configured.
"""

from __future__ import annotations

import asyncio
import hmac
import itertools
import ssl
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from http import HTTPStatus
from typing import Any, Final

import numpy as np
import structlog
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from openral_core import ROSConfigError
from openral_remote.admission import ServeLimits
from openral_remote.codec import WireFormatError
from openral_remote.config import TlsConfig
from openral_remote.meta import PolicyMeta
from openral_remote.msgpack_numpy import Limits, array_header, decode_tree, packb, unpack_tree
from openral_remote.openpi_profiles import OpenpiProfile
from openral_remote.service import Answer, PolicyService, ServiceTransport
from openral_rskill.base import RSkillBase
from openral_rskill.chunks import ChunkRequest

_log = structlog.get_logger(__name__)

HEALTH_PATH: Final = "/healthz"
ERROR_CLOSE_CODE: Final = 1011
ERROR_CLOSE_REASON: Final = "Internal server error. Message included in previous frame."
START_TIMEOUT_S: Final = 30.0
MAX_ENTRIES: Final = 256
"""Keys and list items of one observation: the profiles' dicts have a handful."""


def auth_header(api_key: str) -> str:
    """The ``Authorization`` header value openpi's client sends for ``api_key``."""
    return f"Api-Key {api_key}"


def server_ssl(tls: TlsConfig) -> ssl.SSLContext:
    """A server TLS context from the (checked) files; with ``mutual``, a client certificate of the CA is required."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    assert tls.cert is not None, "a server needs its certificate"
    assert tls.key is not None, "a server needs its key"
    context.load_cert_chain(tls.cert, tls.key)
    if tls.mutual:
        context.verify_mode = ssl.CERT_REQUIRED
        context.load_verify_locations(tls.ca)
    return context


class OpenpiServer(ServiceTransport):
    """Serves ``skill`` to openpi clients on ``host:port`` until closed (a context manager).

    Args:
        skill: The policy, unconfigured (the service configures and shuts it down).
        meta: What it is (sent in the metadata frame as ``openral``).
        profile: How a client's observation dict maps onto a world state.
        host: The address to bind.
        port: The port (0: any free one; :attr:`port` says which).
        limits: Batching, clients, queue and request limits.
        factory: Another instance per further client of a skill that cannot be shared.
        api_key: When given, the key every client must send.
        tls: When given, ``wss://`` with these (checked) files.
    """

    def __init__(
        self,
        skill: RSkillBase,
        *,
        meta: PolicyMeta,
        profile: OpenpiProfile,
        host: str = "127.0.0.1",
        port: int = 8000,
        limits: ServeLimits | None = None,
        factory: Callable[[], RSkillBase] | None = None,
        api_key: str | None = None,
        tls: TlsConfig | None = None,
    ) -> None:
        self.limits = limits or ServeLimits()
        self.profile = profile
        self.host = host
        self.port = port
        self.service = PolicyService(skill, meta=meta, limits=self.limits, factory=factory, name=f"openpi:{port}")
        self._expected_auth = None if api_key is None else auth_header(api_key).encode("utf-8")
        self._ssl = None if tls is None else server_ssl(tls)
        self._decode_limits = Limits(
            max_bytes=self.limits.max_request_bytes,
            max_entries=MAX_ENTRIES,
            max_elements=self.limits.max_image_pixels * 4,
        )
        self._max_connections = 2 * self.limits.max_clients
        self._connections = 0
        self._ids = itertools.count(1)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Server | None = None
        self._thread: threading.Thread | None = None
        self._metadata = b""
        self._tasks: set[asyncio.Future[None]] = set()

    @property
    def url(self) -> str:
        return f"{'wss' if self._ssl else 'ws'}://{self.host}:{self.port}"

    def start(self) -> None:
        """Warm the policy up, then listen (in a thread of its own); rolled back on failure.

        Raises:
            ROSConfigError: The address cannot be bound.
        """
        try:
            self.service.start()
            meta = self.service.meta
            self._metadata = packb(
                {
                    "action_horizon": meta.chunk_size,
                    "action_dim": len(meta.action_names),
                    "openral": meta.model_dump(mode="json"),
                }
            )
            bound: Future[None] = Future()
            self._thread = threading.Thread(target=self._run, args=(bound,), name="openral-openpi-server", daemon=True)
            self._thread.start()
            bound.result(timeout=START_TIMEOUT_S)
        except OSError as exc:
            self.close()
            raise ROSConfigError(f"cannot listen on {self.host}:{self.port}: {exc}", field="--listen") from None
        except BaseException:
            self.close()
            raise
        _log.info("serving openpi", url=self.url, model_hash=meta.model_hash[:12], max_batch=self.service.batch_limit)

    def close(self) -> None:
        """Stop listening, close the connections, answer what is queued, stop the policy. Idempotent."""
        loop, server = self._loop, self._server
        if loop is not None and server is not None and loop.is_running():
            loop.call_soon_threadsafe(server.close)
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        self.service.close()

    # -- the event loop's thread --------------------------------------------------------------

    def _run(self, bound: Future[None]) -> None:
        try:
            asyncio.run(self._serve(bound))
        except BaseException as exc:
            if not bound.done():
                bound.set_exception(exc)
            else:
                _log.error("openpi server stopped", error=str(exc))

    async def _serve(self, bound: Future[None]) -> None:
        self._loop = asyncio.get_running_loop()
        self._server = await serve(
            self._handle,
            self.host,
            self.port,
            process_request=self._process_request,
            ssl=self._ssl,
            compression=None,
            max_size=self.limits.max_request_bytes,
            max_queue=1,
            ping_interval=None,
        )
        self.port = self._server.sockets[0].getsockname()[1]
        self.service.name = f"openpi:{self.port}"
        bound.set_result(None)
        await self._server.wait_closed()

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        """``/healthz``, the connection limit and the API key, answered before the upgrade."""
        if request.path.split("?", 1)[0] == HEALTH_PATH:
            return connection.respond(HTTPStatus.OK, "OK\n")
        if self._expected_auth is not None and not _authorized(request.headers, self._expected_auth):
            self.service.stats.refused += 1
            return connection.respond(HTTPStatus.UNAUTHORIZED, "an API key is required (Authorization: Api-Key ...)\n")
        if self._connections >= self._max_connections:
            self.service.stats.refused += 1
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "busy: too many connections\n")
        return None

    async def _handle(self, websocket: ServerConnection) -> None:
        """One client episode: reset, metadata, then request/reply until it leaves or fails.

        The metadata goes out at once: the reset waits in the client's queue ahead of its first
        request, so a connection never waits for another client's inference. A refused reset
        (the table full) is answered as an error.
        """
        client = f"openpi-{next(self._ids)}"
        self._connections += 1
        try:
            reset = self._reset(client)
            reset.add_done_callback(lambda done: self._reset_answered(websocket, done))
            await websocket.send(self._metadata)
            previous_ms: float | None = None
            async for message in websocket:
                started = time.perf_counter()
                outcome = await self._infer(client, message)
                if reset.done() and reset.result() is not None:
                    return  # refused: the error is on its way
                if isinstance(outcome, str):
                    await _send_error(websocket, outcome)
                    return
                timing: dict[str, float] = {"infer_ms": outcome.infer_ms, "queue_ms": outcome.queue_ms}
                if previous_ms is not None:
                    timing["prev_total_ms"] = previous_ms
                await websocket.send(packb({"actions": outcome.rows.astype(np.float32), "server_timing": timing}))
                previous_ms = (time.perf_counter() - started) * 1e3
        except ConnectionClosed:
            pass
        finally:
            self._connections -= 1
            self.service.leave(client)

    def _reset(self, client: str) -> asyncio.Future[str | None]:
        """A new episode for ``client``: the future's result is ``None``, or the error text when refused."""
        loop = asyncio.get_running_loop()
        done: asyncio.Future[str | None] = loop.create_future()
        self.service.reset(
            client,
            None,
            done=lambda: _resolve(loop, done, None),
            error=lambda text: _resolve(loop, done, text),
        )
        return done

    def _reset_answered(self, websocket: ServerConnection, done: asyncio.Future[str | None]) -> None:
        error = None if done.cancelled() else done.result()
        if error is not None:
            task = asyncio.ensure_future(_send_error(websocket, error))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _infer(self, client: str, message: str | bytes) -> Answer | str:
        """The answer to one request, or an error text (a refusal is decided here, before any array is decoded)."""
        if isinstance(message, str):
            return self._refused("refused: a request is a binary msgpack frame, not text")
        try:
            tree = unpack_tree(message, limits=self._decode_limits)
            self.profile.check(tree, reads=self.service.meta.observation)
            _check_pixels(tree, self.limits)
        except WireFormatError as exc:
            return self._refused(f"refused: {exc}")
        loop = asyncio.get_running_loop()
        outcome: asyncio.Future[Answer | str] = loop.create_future()
        self.service.infer(
            client,
            lambda: self._request(tree),
            answer=lambda answer: _resolve(loop, outcome, answer),
            error=lambda text: _resolve(loop, outcome, text),
            request_bytes=len(message),
        )
        return await outcome

    def _refused(self, text: str) -> str:
        self.service.stats.refused += 1
        return text

    def _request(self, tree: Any) -> ChunkRequest:
        """The checked tree as a chunk request (on the service's worker: arrays decoded, images reoriented)."""
        obs = decode_tree(tree, limits=self._decode_limits)
        return ChunkRequest(world=self.profile.world(obs, stamp_ns=time.time_ns()))


def _authorized(headers: Headers, expected: bytes) -> bool:
    given = headers.get("Authorization", "")
    return hmac.compare_digest(given.encode("utf-8", "replace"), expected)


def _check_pixels(tree: Any, limits: ServeLimits) -> None:
    """Refuse an image (an array of 3 dimensions) over ``max_image_pixels`` (its header only)."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if not isinstance(node, dict):
            continue
        header = array_header(node)
        if header is None:
            stack.extend(node.values())
        elif len(header.shape) == 3:
            height, width = sorted(header.shape)[1:]  # channels first or last: the two largest are the picture
            if height * width > limits.max_image_pixels:
                raise WireFormatError(
                    f"an image of {list(header.shape)} is over the server's {limits.max_image_pixels} pixels"
                )


def _resolve(loop: asyncio.AbstractEventLoop, future: asyncio.Future[Any], value: Any) -> None:
    """Hand ``value`` to ``future`` on its loop (from any thread); nothing if it was cancelled meanwhile."""

    def settle() -> None:
        if not future.done():
            future.set_result(value)

    loop.call_soon_threadsafe(settle)


async def _send_error(websocket: ServerConnection, text: str) -> None:
    """openpi's error convention: the message as a text frame, then close 1011."""
    line = " ".join(text.split())[:1000]
    try:
        await websocket.send(line)
        await websocket.close(ERROR_CLOSE_CODE, ERROR_CLOSE_REASON)
    except ConnectionClosed:
        pass


__all__ = ["HEALTH_PATH", "OpenpiServer", "auth_header", "server_ssl"]
