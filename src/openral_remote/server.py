"""``PolicyServer``: one skill served over Zenoh request/reply, for robots whose computer cannot run it.

* ``<prefix>/infer``: an observation (:mod:`openral_remote.observation`) in, ``{"chunk": rows}``
  out. One worker thread infers, in arrival order. **Latest wins**: a request still waiting when
  a newer one comes from the same client is answered at once with the error ``superseded`` (the
  client has moved on; inferring it would only delay the newer one).
* ``<prefix>/meta``: :class:`openral_remote.meta.PolicyMeta`, answered on Zenoh's thread.
* ``<prefix>/reset``: a new episode (``{"seed": n}``), run by the worker between inferences.
* ``<prefix>/alive``: a liveliness token, declared only once the policy is configured and warm,
  and withdrawn first on the way out; a SIGKILLed server's token is withdrawn by Zenoh itself.

The request's attachment carries the client's id, its sequence number and the W3C
``traceparent``: the server's inference span is a child of the robot's request span, one trace
across both machines. Replies to requests are finalised (the ``Query`` dropped) as soon as they are
answered, so a client never waits out its timeout on a request the server is done with.
"""

from __future__ import annotations

import collections
import json
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import structlog

from openral_core import ROSConfigError
from openral_observability import semconv, tracer
from openral_observability.propagation import extract
from openral_remote.codec import WireFormatError, decode, encode
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.meta import PolicyMeta
from openral_remote.observation import world_from_fields
from openral_remote.session import open_session
from openral_rskill.base import RSkillBase
from openral_rskill.chunks import ChunkRequest

_log = structlog.get_logger(__name__)

ERROR_SUPERSEDED = "superseded"
ERROR_SHUTTING_DOWN = "shutting down"
ALIVE_CHECK_TIMEOUT_S = 1.0
"""How long the start-up check waits for a live server's token (peers answer at once when connected)."""


def attachment_fields(attachment: Any) -> dict[str, Any]:
    """The JSON object in a request's attachment (empty when there is none or it is not one)."""
    if attachment is None:
        return {}
    try:
        value = json.loads(attachment.to_bytes())
    except (ValueError, UnicodeDecodeError):
        return {}
    return value if isinstance(value, dict) else {}


@dataclass
class ServerStats:
    """What a server has done since it started."""

    served: int = 0
    superseded: int = 0
    errors: int = 0
    resets: int = 0


@dataclass
class _Job:
    query: Any
    kind: str
    client: str = ""
    attachment: dict[str, Any] = field(default_factory=dict)
    payload: bytes = b""
    received_ns: int = 0


class PolicyServer:
    """Serves ``skill`` on the keys of ``keys`` until closed (a context manager).

    Args:
        skill: The policy, unconfigured: the server configures, activates and shuts it down.
        keys: Where it is served.
        zenoh: The session's settings (listen endpoints for the robots to connect to).
        meta: What the policy is (published on the ``meta`` key).
    """

    def __init__(self, skill: RSkillBase, *, keys: PolicyKeys, zenoh: ZenohConfig, meta: PolicyMeta) -> None:
        self.skill = skill
        self.keys = keys
        self.zenoh = zenoh
        self.meta = meta
        self.stats = ServerStats()
        self._meta_bytes = meta.to_bytes()
        self._jobs: collections.deque[_Job] = collections.deque()
        self._wake = threading.Condition()
        self._closed = False
        self._session: Any = None
        self._declared: list[Any] = []
        self._token: Any = None
        self._worker: threading.Thread | None = None

    def __enter__(self) -> PolicyServer:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Warm the policy up, declare the keys, then (last) the liveliness token; rolled back on failure.

        Raises:
            ROSConfigError: Another server already holds the key's liveliness token (checked before
                the warm-up and again just before declaring): two servers would answer one robot.
        """
        try:
            self._session = open_session(self.zenoh)
            self._refuse_if_served()
            started = time.perf_counter()
            self.skill.configure()
            self.skill.activate()
            self.meta = self.meta.model_copy(update={"warmup_ms": (time.perf_counter() - started) * 1e3})
            self._meta_bytes = self.meta.to_bytes()
            self._refuse_if_served()
            self._worker = threading.Thread(target=self._work, name="openral-policy-server", daemon=True)
            self._worker.start()
            self._declared = [
                self._session.declare_queryable(self.keys.meta, self._on_meta, complete=True),
                self._session.declare_queryable(self.keys.infer, self._on_infer, complete=True),
                self._session.declare_queryable(self.keys.reset, self._on_reset, complete=True),
            ]
            self._token = self._session.liveliness().declare_token(self.keys.alive)
        except BaseException:
            self.close()
            raise
        _log.info("serving", key=self.keys.prefix, listen=self.zenoh.listen, model_hash=self.meta.model_hash[:12])

    def close(self) -> None:
        """Withdraw the token first (robots fall back at once), answer what is queued, stop. Idempotent."""
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        with self._wake:
            self._closed = True
            pending = list(self._jobs)
            self._jobs.clear()
            self._wake.notify_all()
        for job in pending:
            _reply_error(job.query, ERROR_SHUTTING_DOWN)
        if self._worker is not None:
            self._worker.join(timeout=5.0)
            self._worker = None
        for declared in self._declared:
            declared.undeclare()
        self._declared = []
        if self._session is not None:
            self._session.close()
            self._session = None
        self.skill.shutdown()

    def _refuse_if_served(self) -> None:
        """Raise when a server reachable from this session already declares the key's liveliness token."""
        replies = self._session.liveliness().get(self.keys.alive, timeout=ALIVE_CHECK_TIMEOUT_S)
        if any(reply.ok is not None for reply in replies):
            raise ROSConfigError(
                f"{self.keys.prefix} is already served: another policy server holds its liveliness token "
                f"{self.keys.alive}",
                hint="stop that server first, or serve this policy under another name (--name)",
            )

    # -- Zenoh's threads -------------------------------------------------------------------

    def _on_meta(self, query: Any) -> None:
        query.reply(self.keys.meta, self._meta_bytes)
        query.drop()

    def _on_reset(self, query: Any) -> None:
        self._enqueue(_Job(query, "reset", payload=_payload(query)))

    def _on_infer(self, query: Any) -> None:
        attachment = attachment_fields(query.attachment)
        job = _Job(
            query,
            "infer",
            client=str(attachment.get("client", "")),
            attachment=attachment,
            payload=_payload(query),
            received_ns=time.monotonic_ns(),
        )
        self._enqueue(job)

    def _enqueue(self, job: _Job) -> None:
        """Queue ``job``; an inference still waiting for the same client is taken out and answered ``superseded``."""
        superseded: list[_Job] = []
        with self._wake:
            accepted = not self._closed
            if accepted:
                if job.kind == "infer" and job.client:
                    superseded = [old for old in self._jobs if old.kind == "infer" and old.client == job.client]
                    for old in superseded:
                        self._jobs.remove(old)
                self._jobs.append(job)
                self._wake.notify()
        for old in superseded:
            self.stats.superseded += 1
            _reply_error(old.query, ERROR_SUPERSEDED)
        if not accepted:
            _reply_error(job.query, ERROR_SHUTTING_DOWN)

    # -- the worker ------------------------------------------------------------------------

    def _work(self) -> None:
        while True:
            with self._wake:
                while not self._jobs and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                job = self._jobs.popleft()
            if job.kind == "reset":
                self._reset(job)
            else:
                self._infer(job)

    def _reset(self, job: _Job) -> None:
        try:
            request = json.loads(job.payload or b"{}")
            seed = request.get("seed") if isinstance(request, dict) else None
            if self.skill.last_error is not None:
                self.skill.recover()
                self.skill.activate()
            self.skill.reset(seed=None if seed is None else int(seed))
        except Exception as exc:
            self.stats.errors += 1
            _reply_error(job.query, f"reset failed: {exc}")
            return
        self.stats.resets += 1
        job.query.reply(self.keys.reset, b"{}")
        job.query.drop()

    def _infer(self, job: _Job) -> None:
        queue_ms = (time.monotonic_ns() - job.received_ns) / 1e6
        carrier: dict[str, str] = {
            key: str(job.attachment[key]) for key in ("traceparent", "tracestate") if key in job.attachment
        }
        attributes: dict[str, str | float | int] = {
            semconv.ATTR_REMOTE_KEY: self.keys.infer,
            semconv.ATTR_REMOTE_QUEUE_MS: queue_ms,
            semconv.ATTR_REMOTE_REQUEST_BYTES: len(job.payload),
        }
        with tracer().start_as_current_span(
            semconv.SPAN_REMOTE_INFER, context=extract(carrier), attributes=attributes
        ) as span:
            try:
                reply = self._chunk_reply(job, queue_ms)
            except Exception as exc:
                self.stats.errors += 1
                span.record_exception(exc)
                span.set_attribute(semconv.ATTR_REMOTE_OUTCOME, "error")
                _reply_error(job.query, f"{type(exc).__name__}: {exc}")
                return
            span.set_attributes({semconv.ATTR_REMOTE_OUTCOME: "ok", semconv.ATTR_REMOTE_REPLY_BYTES: len(reply)})
        self.stats.served += 1
        job.query.reply(self.keys.infer, reply)
        job.query.drop()

    def _chunk_reply(self, job: _Job, queue_ms: float) -> bytes:
        try:
            world = world_from_fields(decode(job.payload))
        except WireFormatError as exc:
            raise WireFormatError(f"bad request: {exc}") from None
        if self.skill.last_error is not None:  # an earlier inference failed: try again from a clean state
            self.skill.recover()
            self.skill.activate()
        started = time.perf_counter()
        rows = np.asarray(self.skill.step_chunk(ChunkRequest(world)), dtype=np.float64)  # the chunk, as one array
        infer_ms = (time.perf_counter() - started) * 1e3
        if rows.ndim != 2 or rows.shape[1] != len(self.meta.action_names):
            dims = len(self.meta.action_names)
            raise ROSConfigError(f"the policy returned rows of shape {rows.shape}, not (n, {dims})")
        return encode({"chunk": rows, "infer_ms": infer_ms, "queue_ms": queue_ms, "model_hash": self.meta.model_hash})


def _payload(query: Any) -> bytes:
    payload = query.payload
    return b"" if payload is None else bytes(payload.to_bytes())


def _reply_error(query: Any, text: str) -> None:
    try:
        query.reply_err(text.encode("utf-8"))
    finally:
        query.drop()
