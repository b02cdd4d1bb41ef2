"""``VlaEvalServer``: any skill served to vla-eval's evaluation harness (its model-server protocol, version 1).

vla-eval (allenai/vla-evaluation-harness) runs a benchmark (LIBERO, SimplerEnv, CALVIN...) and
asks a model server over a websocket for one action per step. What this server speaks:

* **Messages**: binary frames, each ``msgpack({"type", "payload", "seq", "timestamp"})`` in
  vla-eval's dialect (:mod:`openral_remote.msgpack_numpy`: str-keyed arrays, PNG images).
  ``hello`` is answered with ``hello`` (protocol 1, the action and observation specs of the
  profile, the ``observation_params`` the benchmark should send, and openral's own policy meta
  under ``openral``: robot, skill, chunk size, model hash). ``episode_start`` starts a new
  episode of the connection (seeded with the task's ``episode_idx`` when it gives one) and is not
  answered; ``observation`` is answered ``action {"actions": float32 (dims,)}`` with the request's
  ``seq``; ``episode_end`` is not answered. A message that cannot be served is answered ``error
  {"error": text}`` with its ``seq`` and the connection stays open.
* **Chunks**: the harness takes one action per step. A chunk's rows are handed out one per
  observation, server-side and per connection (``rows``: how many before asking the policy again),
  anchored as the chunk executor does (:mod:`openral_rskill.anchoring`); only the observation that
  needs a new chunk goes through the policy.
* **Observations** become a :class:`~openral_core.WorldState` as the profile says
  (:mod:`openral_remote.vla_eval_observation`); only the cameras the policy reads are decoded.
* **The policy** runs in :class:`~openral_remote.service.PolicyService`: admission, the fair
  per-client queue and batching are the Zenoh server's; each connection is one client.
* **Modes**: sync (the harness waits for each action) and live (observations on the wall clock,
  actions whenever they are ready; an observation overtaken by a newer one is dropped unanswered).
* **HTTP**: ``GET /health`` → ``200 {"status": "ok"}`` (the socket listens only once the policy is
  warm), ``GET /config`` → the batching settings (read-only here: restart to change them).
* **Access**: an API key, when set, must come as ``Authorization: Api-Key KEY`` (compared in
  constant time; vla-eval 0.8.0's client sends no headers, so only a proxy that adds it gets in),
  and TLS makes it ``wss://`` (the harness must trust the certificate).

Hostile input is bounded: the frame size (``max_request_bytes``, the websocket closes with 1009
above it), the message's depth, entries, dtypes and array sizes (the codec), every image's pixels
from its header before it is decoded, the number of connections, the replies a client leaves unread
(``MAX_UNREAD``, then it is closed), and the text fields' lengths.
"""

from __future__ import annotations

import asyncio
import hmac
import itertools
import json
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any, Final
from urllib.parse import urlparse

import numpy as np
import structlog

from openral_core import ROSConfigError, WorldState
from openral_remote import msgpack_numpy
from openral_remote.admission import ImagesRead, ServeLimits, check_seed
from openral_remote.codec import WireFormatError
from openral_remote.config import TlsConfig
from openral_remote.meta import PolicyMeta
from openral_remote.openpi_server import auth_header, server_ssl
from openral_remote.service import ERROR_SUPERSEDED, Answer, PolicyService, ServiceTransport
from openral_remote.vla_eval_observation import MAX_TEXT, MAX_VALUES, PROFILES, ObservationReader, VlaEvalProfile
from openral_rskill.anchoring import ActionRepresentation, Anchor
from openral_rskill.base import RSkillBase
from openral_rskill.chunks import ChunkRequest

_log = structlog.get_logger(__name__)

PROTOCOL_VERSION: Final = 1
MESSAGE_TYPES: Final = frozenset({"hello", "observation", "action", "episode_start", "episode_end", "error"})
DEFAULT_PORT: Final = 8000
CLOSE_TIMEOUT_S: Final = 1.0
MAX_UNREAD: Final = 64
"""Replies a connection may leave unsent (its client not reading) before it is closed."""
"""How long a closing connection waits for its client's side (a client that never answers holds no shutdown up)."""


def check_servable(meta: PolicyMeta) -> None:
    """Refuse a policy whose rows need what vla-eval's observations never carry.

    Raises:
        ROSConfigError: End-effector delta rows anchored on a privileged position.
    """
    anchor = meta.anchor
    if anchor.representation is ActionRepresentation.DELTA_EE and anchor.position_key is not None:
        raise ROSConfigError(
            f"{meta.skill_id} cannot be served to vla-eval: its rows are anchored on the privileged value "
            f"{anchor.position_key!r}, which vla-eval's observations do not carry",
            field="--skill",
        )


@dataclass
class _Connection:
    """One harness connection: its client id, episode and the rows left of its last chunk."""

    client: str
    mode: str = "sync"
    episode: int = 0
    """Bumped by each ``episode_start``: a chunk asked for in an earlier episode is dropped."""
    tick: int = 0
    targets: np.ndarray | None = None
    next_row: int = 0
    unread: int = 0
    """Replies being sent (waiting on the client to read)."""

    def sent(self, _task: asyncio.Future[Any]) -> None:
        self.unread -= 1


@dataclass(frozen=True)
class _Asked:
    """An observation sent to the policy, and where its answer goes."""

    ws: Any
    conn: _Connection
    episode: int
    seq: int
    observed: WorldState
    """The observation without its pixels (its ``stamp_ns`` is its tick)."""


class VlaEvalServer(ServiceTransport):
    """Serves ``skill`` to vla-eval's harness on ``ws://host:port`` until closed (a context manager).

    Args:
        skill: The policy, unconfigured: the server configures, activates and shuts it down.
        meta: What the policy is (its action names are the action's dimensions).
        host / port: Where to listen (port 0: any free one, see :attr:`port`).
        profile: How observations map onto a world state (:data:`PROFILES`).
        limits: Batching, clients, queue and request limits.
        factory: Another unconfigured instance, for each further client of a skill that cannot be shared.
        rows: Rows of each chunk handed out before the policy is asked again (``None``: all).
        api_key: When given, the key every client must send.
        tls: When given, ``wss://`` with these (checked) files.
    """

    def __init__(
        self,
        skill: RSkillBase,
        *,
        meta: PolicyMeta,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        profile: VlaEvalProfile | None = None,
        limits: ServeLimits | None = None,
        factory: Callable[[], RSkillBase] | None = None,
        rows: int | None = None,
        api_key: str | None = None,
        tls: TlsConfig | None = None,
    ) -> None:
        check_servable(meta)
        self._expected_auth = None if api_key is None else auth_header(api_key).encode("utf-8")
        self._ssl = None if tls is None else server_ssl(tls)
        self.host = host
        self.port = port
        self.profile = profile or PROFILES["plain"]
        self.limits = limits or ServeLimits()
        self.rows = rows
        self.service = PolicyService(skill, meta=meta, limits=self.limits, factory=factory, name=f"vla-eval:{port}")
        self._images = ImagesRead.of(meta.observation)
        self._codec_limits = msgpack_numpy.Limits(
            max_bytes=self.limits.max_request_bytes, max_elements=max(self.limits.max_image_pixels * 4, MAX_VALUES)
        )
        self._reader = ObservationReader(
            self.profile, images=self._images, max_image_pixels=self.limits.max_image_pixels, limits=self._codec_limits
        )
        self._anchor: Anchor = meta.anchor.build()
        self._ids = itertools.count()
        self._connections = 0
        self._max_connections = self.limits.max_clients * 2
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._failure: BaseException | None = None
        self._sending: set[asyncio.Future[Any]] = set()

    @property
    def url(self) -> str:
        return f"{'wss' if self._ssl else 'ws'}://{self.host}:{self.port}"

    def start(self) -> None:
        """Warm the policy up, then listen (so ``/health`` answers only once it can serve).

        Raises:
            ROSConfigError: The address cannot be listened on.
        """
        self.service.start()
        self._thread = threading.Thread(target=self._run, name="openral-vla-eval", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._failure is not None:
            self.close()
            raise ROSConfigError(f"cannot listen on {self.host}:{self.port}: {self._failure}", field="--listen")
        _log.info("serving vla-eval", url=self.url, model_hash=self.meta.model_hash[:12])

    def close(self) -> None:
        """Stop listening, close the connections, answer what is queued, shut the policy down. Idempotent."""
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(timeout=10.0)
            self._thread = None
        self.service.close()

    # -- the event loop's thread -----------------------------------------------------------

    def _run(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # reported by start(); never lost in a thread
            self._failure = exc
            self._ready.set()

    async def _serve(self) -> None:
        from websockets.asyncio.server import serve  # noqa: PLC0415 (the 'remote' extra)

        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with serve(
            self._handle,
            self.host,
            self.port,
            process_request=self._http,
            compression=None,
            max_size=self.limits.max_request_bytes,
            ping_interval=None,
            close_timeout=CLOSE_TIMEOUT_S,
            ssl=self._ssl,
        ) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._ready.set()
            await self._stop.wait()

    def _http(self, connection: Any, request: Any) -> Any:
        """``/health`` and ``/config``; a connection over the limit is refused before its handshake."""
        path = urlparse(request.path).path
        if path == "/health":
            return _json_response(connection, HTTPStatus.OK, {"status": "ok"})
        if self._expected_auth is not None:
            given = request.headers.get("Authorization", "").encode("utf-8", "replace")
            if not hmac.compare_digest(given, self._expected_auth):
                self.service.stats.refused += 1
                return connection.respond(HTTPStatus.UNAUTHORIZED, "an API key is required (Authorization: Api-Key)\n")
        if path == "/config":
            config = {"max_batch_size": self.limits.max_batch, "max_wait_time": self.limits.max_wait_ms / 1e3}
            if urlparse(request.path).query:
                errors = ["read-only: restart openral serve with --max-batch / --max-wait-ms"]
                return _json_response(connection, HTTPStatus.UNPROCESSABLE_ENTITY, {"errors": errors})
            return _json_response(connection, HTTPStatus.OK, {"applied": {}, "config": config})
        if self._connections >= self._max_connections:
            self.service.stats.refused += 1
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "too many connections\n")
        return None

    async def _handle(self, ws: Any) -> None:
        conn = _Connection(client=f"vla-eval-{next(self._ids)}")
        self._connections += 1
        try:
            async for data in ws:
                await self._on_message(ws, conn, data)
        except Exception as exc:  # a connection that dies mid-message is that client's end, never the server's
            _log.info("vla-eval client gone", client=conn.client, reason=type(exc).__name__)
        finally:
            self._connections -= 1
            self.service.leave(conn.client)

    async def _on_message(self, ws: Any, conn: _Connection, data: Any) -> None:
        seq = 0
        try:
            if not isinstance(data, bytes):
                raise WireFormatError("text frames are not messages (binary msgpack only)")
            kind, payload, seq = _envelope(msgpack_numpy.unpack_tree(data, limits=self._codec_limits))
            if kind == "hello":
                await ws.send(_pack("hello", self._hello(payload), seq))
            elif kind == "episode_start":
                self._episode_start(conn, payload)
            elif kind == "observation":
                self._observation(ws, conn, payload, seq, len(data))
            elif kind == "episode_end":
                conn.targets = None
            elif kind == "error":
                _log.info("vla-eval client reported an error", client=conn.client, error=str(payload)[:200])
            else:
                raise WireFormatError(f"a client does not send {kind!r} messages")
        except (WireFormatError, ROSConfigError, ValueError, KeyError) as exc:  # a malformed field, or a state
            self.service.stats.refused += 1  # the policy's anchor needs and the observation lacks
            await ws.send(_pack("error", {"error": f"refused: {exc}"}, seq))

    def _hello(self, payload: Mapping[str, Any]) -> dict[str, Any]:
        version = payload.get("protocol_version")
        if version != PROTOCOL_VERSION:
            raise WireFormatError(f"protocol_version {str(version)[:20]!r} is not spoken here (1 is)")
        meta = self.meta
        reads = self._reads
        harness = payload.get("harness_version")
        reply: dict[str, Any] = {
            "harness_version": harness[:MAX_TEXT] if isinstance(harness, str) else "",
            "protocol_version": PROTOCOL_VERSION,
            "model_server": f"openral:{meta.skill_id}",
            "capabilities": {},
            "openral": meta.model_dump(mode="json"),
        }
        params = {name: True for name, reader in self.profile.observation_params.items() if reads(reader)}
        if params:
            reply["observation_params"] = params
        if self.profile.action_spec:
            reply["action_spec"] = dict(self.profile.action_spec)
        if self.profile.observation_spec:
            reply["observation_spec"] = dict(self.profile.observation_spec)
        return reply

    def _reads(self, reader: str) -> bool:
        """Whether the policy reads ``reader`` (a world-state field, or ``images.<camera>``)."""
        if reader.startswith("images."):
            return self._images.reads(reader.removeprefix("images."))
        fields = self.meta.observation
        return not fields or reader in fields

    def _episode_start(self, conn: _Connection, payload: Mapping[str, Any]) -> None:
        task = payload.get("task")
        index = task.get("episode_idx") if isinstance(task, dict) else None
        seed = check_seed(index if isinstance(index, int) and not isinstance(index, bool) else None)
        mode = payload.get("mode")
        conn.mode = "live" if mode == "live" else "sync"
        conn.episode += 1
        conn.tick = 0
        conn.targets = None

        def failed(text: str) -> None:
            _log.warning("vla-eval episode reset failed", client=conn.client, error=text)

        self.service.reset(conn.client, seed, done=lambda: None, error=failed)

    def _observation(self, ws: Any, conn: _Connection, payload: Mapping[str, Any], seq: int, size: int) -> None:
        # Everything but the pixels is read here (small): a malformed observation is refused before it counts.
        observed = self._reader.world(payload, stamp_ns=conn.tick)
        asked = _Asked(ws, conn, conn.episode, seq, observed)
        targets = conn.targets
        if targets is not None and conn.next_row < len(targets):
            command = self._anchor.to_command(targets[conn.next_row], observed)
            conn.next_row += 1
            conn.tick += 1
            self._send(conn, ws, _pack("action", {"actions": np.asarray(command, dtype=np.float32)}, seq))
            return
        self._reader.check_images(payload)
        conn.tick += 1  # a refused observation is no step: the harness does not act on it
        conn.targets = None
        loop = self._loop
        assert loop is not None

        def decoded() -> ChunkRequest:
            frames = self._reader.frames(payload, observed.stamp_ns)  # decoding pixels is the worker's work
            return ChunkRequest(world=observed.model_copy(update={"image_frames": frames}), obs_tick=observed.stamp_ns)

        def answer(answer: Answer) -> None:
            loop.call_soon_threadsafe(self._on_chunk, asked, answer.rows)

        def error(text: str) -> None:
            loop.call_soon_threadsafe(self._on_error, asked, text)

        self.service.infer(conn.client, decoded, answer=answer, error=error, request_bytes=size)

    def _on_chunk(self, asked: _Asked, rows: np.ndarray) -> None:
        conn = asked.conn
        if asked.episode != conn.episode:
            return  # asked in an episode that has ended
        try:
            if len(rows) == 0:
                raise WireFormatError("the policy returned no rows")
            targets = self._anchor.to_targets(rows[: self.rows] if self.rows else rows, asked.observed)
            command = self._anchor.to_command(targets[0], asked.observed)
        except Exception as exc:  # an anchor without the state it needs: this client's error, not the loop's
            self._on_error(asked, f"{type(exc).__name__}: {exc}")
            return
        conn.targets, conn.next_row = targets, 1
        self._send(conn, asked.ws, _pack("action", {"actions": np.asarray(command, dtype=np.float32)}, asked.seq))

    def _on_error(self, asked: _Asked, text: str) -> None:
        if asked.episode != asked.conn.episode or (asked.conn.mode == "live" and text == ERROR_SUPERSEDED):
            return  # asked in an ended episode, or a live observation overtaken by a newer one: no answer
        self._send(asked.conn, asked.ws, _pack("error", {"error": f"observation_failed: {text}"}, asked.seq))

    def _send(self, conn: _Connection, ws: Any, message: bytes) -> None:
        """Send from the loop without waiting on the client (a slow reader holds no one else up).

        A client that leaves ``MAX_UNREAD`` replies unread is closed: its replies never pile up.
        """
        if conn.unread >= MAX_UNREAD:
            task = asyncio.ensure_future(ws.close(1008, "replies left unread"))
        else:
            conn.unread += 1
            task = asyncio.ensure_future(ws.send(message))
            task.add_done_callback(conn.sent)
        self._sending.add(task)
        task.add_done_callback(self._sent)

    def _sent(self, task: asyncio.Future[Any]) -> None:
        self._sending.discard(task)
        if not task.cancelled():
            task.exception()  # retrieved: a client that left mid-reply is not an error of the server


def _envelope(tree: Any) -> tuple[str, Mapping[str, Any], int]:
    """``(type, payload, seq)`` of a message, checked.

    Raises:
        WireFormatError: Not a vla-eval message.
    """
    if not isinstance(tree, dict):
        raise WireFormatError("a message is a map")
    kind, payload, seq = tree.get("type"), tree.get("payload"), tree.get("seq")
    if not isinstance(seq, int) or isinstance(seq, bool) or not -(1 << 63) <= seq < (1 << 63):
        raise WireFormatError("seq is not a 64-bit integer")
    if kind not in MESSAGE_TYPES:
        raise WireFormatError(f"unknown message type {str(kind)[:40]!r}")
    if not isinstance(payload, dict):
        raise WireFormatError("payload is not a map")
    return str(kind), payload, seq


def _pack(kind: str, payload: Mapping[str, Any], seq: int) -> bytes:
    message = {"type": kind, "payload": payload, "seq": seq, "timestamp": time.time()}
    return msgpack_numpy.packb(message, dialect="vla_eval", image_format="raw")


def _json_response(connection: Any, status: HTTPStatus, body: Mapping[str, Any]) -> Any:
    response = connection.respond(status, json.dumps(body) + "\n")
    del response.headers["Content-Type"]
    response.headers["Content-Type"] = "application/json"
    return response


def serve_vla_eval(
    skill: RSkillBase,
    *,
    meta: PolicyMeta,
    host: str,
    port: int,
    limits: ServeLimits,
    factory: Callable[[], RSkillBase],
    api_key: str | None,
    tls: TlsConfig | None,
    profile: str = "libero",
) -> VlaEvalServer:
    """The server ``openral serve --protocol vla-eval`` runs (see :class:`VlaEvalServer`).

    Raises:
        ROSConfigError: An unknown profile, or a policy vla-eval's observations cannot drive.
    """
    if profile not in PROFILES:
        raise ROSConfigError(
            f"no vla-eval profile {profile!r}", field="--vla-eval-profile", hint=f"one of {sorted(PROFILES)}"
        )
    return VlaEvalServer(
        skill,
        meta=meta,
        host=host,
        port=port,
        profile=PROFILES[profile],
        limits=limits,
        factory=factory,
        api_key=api_key,
        tls=tls,
    )


__all__ = [
    "DEFAULT_PORT",
    "PROFILES",
    "PROTOCOL_VERSION",
    "VlaEvalProfile",
    "VlaEvalServer",
    "check_servable",
    "serve_vla_eval",
]
