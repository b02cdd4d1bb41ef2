"""``RemotePolicyClient``: asks a policy server for chunks, with a deadline, and knows when it is gone.

Outcomes of a request, each its own exception so the executor can count it:

* a chunk;
* **no reply at all**: nobody serves the key (the server died): :class:`ServerUnavailable`, and
  the server is marked down until its liveliness token returns;
* no answer by the deadline (a hung server): :class:`~openral_remote.session.RemoteTimeout`, a
  ``TimeoutError`` (the executor counts it late);
* ``superseded``: a newer request of ours overtook it: :class:`RemoteSuperseded`;
* another error of the server (its policy failed): :class:`~openral_remote.session.PeerError`.

Requests go through :mod:`openral_remote.session`, which translates Zenoh's errors.

A liveliness subscriber marks the server down the moment its token is withdrawn (a clean
shutdown, a SIGKILL noticed by the kernel, or a silent link after the lease), without waiting for
a request to fail. When the token comes back, ``meta`` is fetched again on a thread of its own: a
server that returns with another model (a different hash or shape) is refused, and stays down,
unless ``on_model_change`` is ``accept`` and the shapes still fit.

**Pinning.** The client keeps the Zenoh id of the server it first reached (the replier of its
first ``meta``, or ``server_id`` given up front) and acts only on replies from it: a chunk from
another id is not used, and a server that comes back under another id is refused like another
model, unless ``on_server_change`` is ``accept``. ``openral serve`` keeps its id across restarts,
so the real server is taken back. An id can be claimed by anyone who knows it: pinning stops a
peer that copied the public ``meta`` from being taken for the server, not one that also copied
the id; with TLS on, the certificate is what proves who the server is.
"""

from __future__ import annotations

import itertools
import json
import threading
import time
import uuid
from typing import Any, Literal

import numpy as np
import structlog

from openral_core import ROSConfigError, ROSDependencyMissing, ROSUnavailable, WorldState
from openral_observability import metrics, semconv, tracer
from openral_observability.propagation import inject
from openral_remote.codec import decode, encode
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.meta import PolicyMeta
from openral_remote.observation import request_fields
from openral_remote.server import ERROR_SUPERSEDED
from openral_remote.session import Answer, NoReply, PeerError, Querier, RemoteTimeout, ask, open_session
from openral_rskill.chunks import ChunkRequest

try:
    import zenoh
    from zenoh import shm
except ImportError as exc:
    raise ROSDependencyMissing("zenoh", extra="remote", needed_for="remote inference over Zenoh") from exc

__all__ = [
    "SHAPE_FIELDS",
    "PeerError",
    "RemotePolicyClient",
    "RemoteSuperseded",
    "RemoteTimeout",
    "ServerRefused",
    "ServerUnavailable",
    "check_compatible",
]

_log = structlog.get_logger(__name__)

_SHM_POOL_BYTES = 32 << 20
SHAPE_FIELDS = frozenset(
    {"chunk_size", "action_names", "control_mode", "anchor", "dt_s", "observation_steps", "schema_version"}
)
"""Meta fields a running robot cannot take a change of, whatever ``on_model_change`` says."""


class ServerUnavailable(ROSUnavailable):
    """No policy server answers (none is alive, or a request got no reply)."""


class RemoteSuperseded(ROSUnavailable):
    """The server dropped the request for a newer one of this client."""


class ServerRefused(ServerUnavailable):
    """A peer other than the pinned server answered: its reply is not acted on."""


class RemotePolicyClient:
    """One robot's link to one served policy.

    Args:
        keys: Where the policy is served.
        zenoh: The session's settings (the server's endpoint in ``connect``).
        deadline_ms: A request without a reply by then fails with :class:`RemoteTimeout`.
        on_model_change: ``refuse`` (default) or ``accept`` a server that returns with another model.
        jpeg_quality: Send RGB/BGR camera images as JPEG of this quality; raw when ``None``.
        server_id: The server's Zenoh id, pinned before connecting; ``None``: the first one reached.
        on_server_change: ``refuse`` (default) or ``accept`` (and pin) a server with another id.
    """

    def __init__(
        self,
        keys: PolicyKeys,
        zenoh: ZenohConfig,
        *,
        deadline_ms: float = 500.0,
        on_model_change: Literal["refuse", "accept"] = "refuse",
        jpeg_quality: int | None = None,
        server_id: str | None = None,
        on_server_change: Literal["refuse", "accept"] = "refuse",
    ) -> None:
        self.keys = keys
        self.zenoh = zenoh
        self.deadline_s = deadline_ms / 1e3
        self.on_model_change = on_model_change
        self.jpeg_quality = jpeg_quality
        self.server_id = server_id
        """The pinned server's Zenoh id: replies from any other are not acted on."""
        self.on_server_change = on_server_change
        self.client_id = uuid.uuid4().hex[:16]
        self.meta: PolicyMeta | None = None
        self.changes: list[str] = []
        """Down and up events, in order (``down``, ``up``, ``refused``): what happened to the link."""
        self._up = False
        self._alive = threading.Event()
        self._seq = itertools.count()
        self._session: Any = None
        self._querier: Querier | None = None
        self._liveliness: Any = None
        self._shm: Any = None
        self._lock = threading.Lock()
        self._generation = 0

    # -- lifecycle -------------------------------------------------------------------------

    def connect(self, timeout_s: float) -> PolicyMeta:
        """Open the session, wait up to ``timeout_s`` for the server to be alive, and read its ``meta``.

        Raises:
            ServerUnavailable: No server became alive in time, or it did not answer ``meta``.
            ROSConfigError: The server's Zenoh id is not the one pinned up front.
        """
        self._session = open_session(self.zenoh)
        try:
            self._querier = Querier(self._session, self.keys.infer, timeout_s=self.deadline_s)
            self._liveliness = self._session.liveliness().declare_subscriber(
                self.keys.alive, self._on_liveliness, history=True
            )
            if not self._alive.wait(timeout_s):
                raise ServerUnavailable(
                    f"no policy server is alive at {self.keys.prefix} (connect {self.zenoh.connect}) "
                    f"after {timeout_s:g} s; start one with 'openral serve'"
                )
            self.meta, replier = self._fetch_meta(timeout_s)
            self._pin(replier)
            self._up = self._alive.is_set()
            if self.zenoh.shared_memory:
                self._shm = _shm_provider()
        except BaseException:
            self.close()
            raise
        return self.meta

    def close(self) -> None:
        """Undeclare everything and close the session. Idempotent."""
        self._up = False
        if self._liveliness is not None:
            self._liveliness.undeclare()
            self._liveliness = None
        if self._querier is not None:
            self._querier.close()
            self._querier = None
        if self._session is not None:
            self._session.close()
            self._session = None

    def available(self) -> bool:
        """Whether the server is up (alive, with the expected model): O(1), read every tick."""
        return self._up

    # -- requests --------------------------------------------------------------------------

    def fetch_meta(self, timeout_s: float) -> PolicyMeta:
        """The server's ``meta`` now (whoever answers it).

        Raises:
            ServerUnavailable: No reply, or not a ``PolicyMeta``.
        """
        return self._fetch_meta(timeout_s)[0]

    def _fetch_meta(self, timeout_s: float) -> tuple[PolicyMeta, str | None]:
        """The server's ``meta`` and the Zenoh id of who answered it."""
        session = self._session
        if session is None:
            raise ServerUnavailable("the client is closed")
        try:
            data, replier = ask(session, self.keys.meta, timeout_s=timeout_s)
        except ROSUnavailable as exc:
            raise ServerUnavailable(f"no answer on {self.keys.meta} ({exc})") from None
        try:
            return PolicyMeta.from_bytes(data), replier
        except ValueError as exc:
            raise ServerUnavailable(f"{self.keys.meta} answered something that is not policy meta: {exc}") from None

    def _pin(self, replier: str | None) -> None:
        """Pin the first server reached, or check it is the one pinned up front."""
        if self.server_id is None or replier == self.server_id:
            self.server_id = replier
            return
        if self.on_server_change == "accept":
            _log.warning("policy server has another id; accepted", key=self.keys.prefix, zenoh_id=replier)
            self.server_id = replier
            return
        raise ROSConfigError(
            f"{self.keys.meta} was answered by Zenoh id {replier}, not the pinned server {self.server_id}",
            field="server_id",
            hint="if that server is the one meant, pin its id (server_id) or set on_server_change: accept",
        )

    def infer(self, request: WorldState | ChunkRequest, *, seed: int | None = None) -> np.ndarray:
        """The chunk the server computes for ``request``: ``(rows, dims)`` float64.

        Args:
            request: The executor's request (its history and prefix within the policy's bounds
                go along), or a bare observation.
            seed: The episode's seed, which the policy's sampling draws from, when the request
                carries none: sent with every request, so a lost reset cannot unseed it.

        Raises:
            ServerUnavailable: The server is down, or nobody answered (it is then marked down).
            ServerRefused: A peer other than the pinned server answered: not acted on, the server marked down.
            RemoteTimeout: No answer before the deadline.
            RemoteSuperseded: The server dropped it for a newer request.
            PeerError: The server answered with another error (its policy failed).
        """
        if not self._up:
            raise ServerUnavailable(f"the policy server at {self.keys.prefix} is down")
        meta = self.meta
        assert meta is not None
        asked = request if isinstance(request, ChunkRequest) else ChunkRequest(request)
        fields, jpeg = request_fields(
            asked,
            meta.observation,
            history=meta.observation_steps - 1,
            prefix_rows=meta.chunk_size,
            seed=seed,
            jpeg_quality=self.jpeg_quality,
        )
        message = encode(fields, jpeg=jpeg)
        payload = self._shared(message)
        size = len(message)
        started = time.perf_counter()
        with tracer().start_as_current_span(
            semconv.SPAN_REMOTE_REQUEST,
            attributes={semconv.ATTR_REMOTE_KEY: self.keys.infer, semconv.ATTR_REMOTE_REQUEST_BYTES: size},
        ) as span:
            attachment: dict[str, Any] = {"client": self.client_id, "seq": next(self._seq)}
            inject(attachment)
            try:
                rows, reply_bytes = self._round_trip(payload, json.dumps(attachment).encode("utf-8"))
            except ROSUnavailable as exc:
                outcome = _outcome(exc)
                span.set_attribute(semconv.ATTR_REMOTE_OUTCOME, outcome)
                metrics.add(semconv.METRIC_REMOTE_FAILURES, 1, {semconv.ATTR_REMOTE_OUTCOME: outcome})
                raise
            span.set_attributes({semconv.ATTR_REMOTE_OUTCOME: "ok", semconv.ATTR_REMOTE_REPLY_BYTES: reply_bytes})
        metrics.histogram(semconv.METRIC_REMOTE_ROUND_TRIP).record((time.perf_counter() - started) * 1e3)
        return rows

    def reset(self, seed: int | None = None) -> None:
        """Start a new episode of this client on the server (waits for it, at most the deadline).

        The server keeps an episode per client: this resets ours only, never another robot's.
        """
        if not self._up:
            raise ServerUnavailable(f"the policy server at {self.keys.prefix} is down")
        body = json.dumps({"seed": seed}).encode("utf-8")
        attachment = json.dumps({"client": self.client_id}).encode("utf-8")
        try:
            reply = ask(self._session, self.keys.reset, body, timeout_s=self.deadline_s, attachment=attachment)
        except PeerError as exc:
            raise _refusal(exc) from None
        except NoReply:
            raise ServerUnavailable(f"no answer on {self.keys.reset}") from None
        self._check_replier(reply, self.keys.reset)

    def _round_trip(self, payload: Any, attachment: bytes) -> tuple[np.ndarray, int]:
        querier = self._querier
        if querier is None:
            raise ServerUnavailable("the client is closed")
        try:
            reply = querier.ask(payload, attachment=attachment)
        except PeerError as exc:
            raise _refusal(exc) from None
        except NoReply:
            self._mark_down("no reply")
            if self._alive.is_set():  # its token is still there: ask for its meta rather than wait for a change
                self._start_recheck()
            raise ServerUnavailable(f"nobody answered on {self.keys.infer}: the policy server is gone") from None
        self._check_replier(reply, self.keys.infer)
        data = reply.payload
        fields = decode(data)
        chunk = fields.get("chunk")
        if not isinstance(chunk, np.ndarray) or chunk.ndim != 2:
            raise ROSUnavailable(f"{self.keys.infer} answered without a chunk")
        meta = self.meta
        if meta is not None and fields.get("model_hash") != meta.model_hash:
            # Another model behind the same key without the server going away: judged as a return.
            self._mark_down("the model changed")
            self._start_recheck()
            raise ServerUnavailable(f"{self.keys.infer} answered from another model; checking its meta")
        return np.asarray(chunk, dtype=np.float64), len(data)  # a view of the reply: no copy, no list

    def _check_replier(self, reply: Answer, key: str) -> None:
        """Refuse a reply from anyone but the pinned server; judged as a return (its ``meta`` is read again)."""
        if reply.replier == self.server_id:
            return
        self._mark_down("another server answered")
        self._start_recheck()
        _log.error("a reply from another server refused", key=key, zenoh_id=reply.replier, pinned=self.server_id)
        raise ServerRefused(f"{key} was answered by Zenoh id {reply.replier}, not the pinned server {self.server_id}")

    def _shared(self, message: bytes) -> Any:
        """The message in shared memory when a pool is there (same-host peers then read it in place)."""
        provider = self._shm
        if provider is None:
            return message
        try:
            buffer = provider.alloc(len(message), shm.GarbageCollect())
        except Exception:  # pool exhausted or unsupported: plain bytes work everywhere
            return message
        buffer[:] = message  # ZShmMut takes bytes only (no buffer protocol): one copy
        return zenoh.ZBytes(buffer)

    # -- liveliness ------------------------------------------------------------------------

    def _on_liveliness(self, sample: Any) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._alive.set()
            if self.meta is not None and not self._up:
                self._start_recheck()
        else:
            self._alive.clear()
            self._mark_down("token withdrawn")

    def _start_recheck(self) -> None:
        """Read ``meta`` again on a thread of its own (never on Zenoh's callback thread)."""
        with self._lock:
            self._generation += 1
            generation = self._generation
        threading.Thread(target=self._recheck, args=(generation,), name="openral-remote-recheck", daemon=True).start()

    def _mark_down(self, why: str) -> None:
        with self._lock:
            was_up, self._up = self._up, False
            self._generation += 1
        if was_up:
            self._change("down")
            _log.warning("policy server down", key=self.keys.prefix, why=why)

    def _recheck(self, generation: int) -> None:
        """The server is alive again: take it back only if it is the pinned one and serves what we expect.

        Its ``meta`` is asked for until it answers, as long as its token stays and nothing newer
        happened (another return, another loss).
        """
        while True:
            try:
                meta, replier = self._fetch_meta(max(self.deadline_s, 1.0))
                break
            except ROSUnavailable as exc:
                _log.warning("policy server alive but its meta is unreadable; asking again", error=str(exc))
            if self._session is None or generation != self._generation or not self._alive.wait(0.5):
                return
            time.sleep(0.5)
        expected = self.meta
        assert expected is not None
        changed = expected.differences(meta)
        refuse = bool(SHAPE_FIELDS.intersection(changed)) or (changed and self.on_model_change == "refuse")
        stranger = replier != self.server_id
        with self._lock:
            if generation != self._generation or not self._alive.is_set():
                return  # went down again meanwhile
            if stranger and self.on_server_change == "refuse":
                self._change("refused")
                _log.error(
                    "a policy server with another Zenoh id is alive; refused (the fallback stays in charge)",
                    key=self.keys.prefix,
                    zenoh_id=replier,
                    pinned=self.server_id,
                )
                return
            if refuse:
                self._change("refused")
                _log.error(
                    "policy server came back with another model; refused (the fallback stays in charge)",
                    key=self.keys.prefix,
                    differs=changed,
                    model_hash=meta.model_hash[:12],
                )
                return
            if changed:
                self.meta = meta
            if stranger:
                _log.warning("policy server has another Zenoh id; accepted", key=self.keys.prefix, zenoh_id=replier)
                self.server_id = replier
            self._up = True
        self._change("up")
        _log.info("policy server up", key=self.keys.prefix, model_hash=meta.model_hash[:12])

    def _change(self, what: str) -> None:
        self.changes.append(what)
        metrics.add(semconv.METRIC_REMOTE_SERVER_CHANGES, 1, {semconv.ATTR_REMOTE_OUTCOME: what})


def _refusal(error: PeerError) -> ROSUnavailable:
    """The server's error answer: superseded by a newer request of ours, or its own failure."""
    if error.text.startswith(ERROR_SUPERSEDED):
        return RemoteSuperseded(f"{error.key}: superseded by a newer request")
    return error


def _outcome(exc: ROSUnavailable) -> str:
    if isinstance(exc, RemoteTimeout):
        return "timeout"
    if isinstance(exc, RemoteSuperseded):
        return "superseded"
    if isinstance(exc, ServerRefused):
        return "refused"
    if isinstance(exc, ServerUnavailable):
        return "unavailable"
    return "error"


def _shm_provider() -> Any:
    try:
        return shm.ShmProvider.default_backend(_SHM_POOL_BYTES)
    except Exception as exc:  # no /dev/shm, or not allowed: plain bytes
        _log.info("no shared memory for requests", error=str(exc))
        return None


def check_compatible(meta: PolicyMeta, *, action_dims: int | None, rate_hz: float, field: str) -> None:
    """Refuse a served policy this robot cannot run (chunk size, action size, step period).

    Raises:
        ROSConfigError: Naming what does not fit.
    """
    if meta.chunk_size < 2:
        raise ROSConfigError(
            f"{meta.policy} returns one row per request; a row cannot arrive in time for its own tick",
            field=field,
            hint="serve a policy that returns chunks (chunk size above 1)",
        )
    if action_dims is not None and len(meta.action_names) != action_dims:
        raise ROSConfigError(
            f"{meta.policy} acts on {len(meta.action_names)} dimensions {meta.action_names}, "
            f"this robot on {action_dims}",
            field=field,
        )
    if abs(meta.dt_s * rate_hz - 1.0) > 1e-6:
        raise ROSConfigError(
            f"{meta.policy} steps every {meta.dt_s:g} s but the loop ticks at {rate_hz:g} Hz",
            field=field,
            hint="run the loop at the policy's rate, or serve it with --rate-hz matching the robot",
        )
