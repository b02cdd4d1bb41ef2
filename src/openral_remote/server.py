"""``PolicyServer``: one policy served over Zenoh request/reply to many robots, for computers that cannot run it.

* ``<prefix>/infer``: a chunk request (:mod:`openral_remote.observation`: the observation, the
  earlier ones the policy reads, the executor's prefix, the robot's episode seed) in,
  ``{"chunk": rows}`` out. Requests are checked from their header before anything is decoded
  (:mod:`openral_remote.admission`), then wait in a fair queue (:mod:`openral_remote.fair_queue`):
  latest wins per client (a request overtaken by a newer one of the same client is answered
  ``superseded`` at once), clients are served in turn, and the queue is bounded. One worker
  thread infers; with ``max_batch`` above 1 and a skill that batches, concurrent clients'
  requests go through the policy as one batch.
* ``<prefix>/reset``: a new episode **of the sender** (``{"seed": n}``, the client's id in the
  attachment): each client has an episode of its own (:mod:`openral_remote.episodes`).
* ``<prefix>/meta``: :class:`openral_remote.meta.PolicyMeta`, answered on Zenoh's thread.
* ``<prefix>/alive``: a liveliness token, declared only once the policy is configured and warm,
  and withdrawn first on the way out; a SIGKILLed server's token is withdrawn by Zenoh itself.

The request's attachment carries the client's id, its sequence number and the W3C
``traceparent``: the server's inference span is a child of the robot's request span, one trace
across both machines, and records the batch it ran in. Replies are finalised (the ``Query``
dropped) as soon as they are answered, so a client never waits out its timeout on a request the
server is done with.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import structlog
from opentelemetry.trace import Span

from openral_core import ROSConfigError
from openral_observability import semconv, tracer
from openral_observability.propagation import extract
from openral_remote.admission import ImagesRead, RequestBounds, ServeLimits, admit, check_seed
from openral_remote.codec import WireFormatError, decode, encode
from openral_remote.config import ZenohConfig
from openral_remote.episodes import ClientEpisode, EpisodeTable
from openral_remote.fair_queue import INFER, RESET, FairQueue, Job
from openral_remote.keys import PolicyKeys
from openral_remote.meta import PolicyMeta
from openral_remote.observation import request_from_fields
from openral_remote.session import alive_behind, open_session
from openral_rskill.base import RSkillBase
from openral_rskill.chunks import ChunkRequest

_log = structlog.get_logger(__name__)

ERROR_SUPERSEDED = "superseded"
ERROR_SHUTTING_DOWN = "shutting down"
ERROR_BUSY = "busy"
ERROR_FULL = "full"
MAX_CLIENT_ID = 64
"""Characters of a client's id kept: the episode table is keyed by it, and a peer picks it."""
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
    refused: int = 0
    """Requests turned away unread: over a limit, a camera the policy does not read, the queue or table full."""
    batches: int = 0
    largest_batch: int = 0


@dataclass
class _Prepared:
    """An inference request decoded and matched with its client's episode and skill."""

    job: Job
    request: ChunkRequest
    skill: RSkillBase
    span: Span
    queue_ms: float


class PolicyServer:
    """Serves ``skill`` on the keys of ``keys`` until closed (a context manager).

    Args:
        skill: The policy, unconfigured: the server configures, activates and shuts it down.
        keys: Where it is served.
        zenoh: The session's settings (listen endpoints for the robots to connect to).
        meta: What the policy is (published on the ``meta`` key).
        limits: Batching, clients, queue and request limits.
        factory: Makes another unconfigured instance of the skill, for each further client of a
            skill that cannot be shared between episodes; without it such a skill serves one
            client at a time.
    """

    def __init__(
        self,
        skill: RSkillBase,
        *,
        keys: PolicyKeys,
        zenoh: ZenohConfig,
        meta: PolicyMeta,
        limits: ServeLimits | None = None,
        factory: Callable[[], RSkillBase] | None = None,
    ) -> None:
        self.skill = skill
        self.keys = keys
        self.zenoh = zenoh
        self.meta = meta
        self.limits = limits or ServeLimits()
        self.stats = ServerStats()
        self._factory = factory
        self._meta_bytes = meta.to_bytes()
        self._images = ImagesRead.of(meta.observation)
        self._bounds = RequestBounds(
            history=meta.observation_steps - 1, prefix_rows=meta.chunk_size, action_dims=len(meta.action_names)
        )
        self._queue = FairQueue(self.limits.max_pending)
        self._episodes: EpisodeTable | None = None
        self._session: Any = None
        self._declared: list[Any] = []
        self._token: Any = None
        self._worker: threading.Thread | None = None

    def __enter__(self) -> PolicyServer:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def clients(self) -> int:
        """Clients with an episode on the server now."""
        return 0 if self._episodes is None else len(self._episodes)

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
            self._episodes = EpisodeTable(self.skill, factory=self._factory, limits=self.limits)
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
        _log.info(
            "serving",
            key=self.keys.prefix,
            listen=self.zenoh.listen,
            model_hash=self.meta.model_hash[:12],
            shared=self._episodes.shared,
            max_batch=self._batch_limit(),
        )

    def close(self) -> None:
        """Withdraw the token first (robots fall back at once), answer what is queued, stop. Idempotent."""
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        for job in self._queue.drain():
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
        if self._episodes is not None:
            self._episodes.retire_all()
        self.skill.shutdown()

    def _refuse_if_served(self) -> None:
        """Raise when a server linked to this session, or behind an endpoint it dials, declares the key's token."""
        replies = self._session.liveliness().get(self.keys.alive, timeout=ALIVE_CHECK_TIMEOUT_S)
        if any(reply.ok is not None for reply in replies) or alive_behind(
            self.zenoh, self.keys.alive, timeout_s=ALIVE_CHECK_TIMEOUT_S
        ):
            raise ROSConfigError(
                f"{self.keys.prefix} is already served: another policy server holds its liveliness token "
                f"{self.keys.alive}",
                hint="stop that server first, or serve this policy under another name (--name)",
            )

    def _batch_limit(self) -> int:
        shared = self._episodes is not None and self._episodes.shared
        return min(self.limits.max_batch, self.skill.batch_capacity()) if shared else 1

    # -- Zenoh's threads -------------------------------------------------------------------

    def _on_meta(self, query: Any) -> None:
        query.reply(self.keys.meta, self._meta_bytes)
        query.drop()

    def _on_reset(self, query: Any) -> None:
        attachment = attachment_fields(query.attachment)
        self._enqueue(Job(query, RESET, client=_client_id(attachment), payload=_payload(query)))

    def _on_infer(self, query: Any) -> None:
        attachment = attachment_fields(query.attachment)
        payload = _payload(query)
        try:
            admit(payload, limits=self.limits, images=self._images, bounds=self._bounds)
        except WireFormatError as exc:
            self.stats.refused += 1
            _reply_error(query, f"refused: {exc}")
            return
        self._enqueue(Job(query, INFER, client=_client_id(attachment), attachment=attachment, payload=payload))

    def _enqueue(self, job: Job) -> None:
        """Queue ``job`` for its client's episode; answer at once what it supersedes or displaces, or it if refused."""
        episodes = self._episodes
        if episodes is None or not episodes.admit(job.client):
            self.stats.refused += 1
            _reply_error(job.query, f"{ERROR_FULL}: the server has {self.limits.max_clients} clients under way")
            return
        job.established = episodes.established(job.client)
        admission = self._queue.put(job)
        for old in admission.superseded:
            self.stats.superseded += 1
            _reply_error(old.query, ERROR_SUPERSEDED)
        for old in admission.displaced:
            self.stats.refused += 1
            _reply_error(old.query, f"{ERROR_BUSY}: displaced by a robot under way")
        if not admission.accepted:
            if self._token is None and not self._declared:
                _reply_error(job.query, ERROR_SHUTTING_DOWN)
            else:
                self.stats.refused += 1
                _reply_error(job.query, f"{ERROR_BUSY}: {self.limits.max_pending} requests are waiting")

    # -- the worker ------------------------------------------------------------------------

    def _work(self) -> None:
        episodes = self._episodes
        assert episodes is not None
        batch_limit = self._batch_limit()  # asked once: a model's batch dimension does not change
        while True:
            jobs = self._queue.take(batch_limit, self.limits.max_wait_ms / 1e3, episodes.active)
            if not jobs:
                return
            if jobs[0].kind == RESET:
                self._reset(jobs[0], episodes.episode(jobs[0].client))
            else:
                self._infer(jobs)

    def _reset(self, job: Job, episode: ClientEpisode) -> None:
        assert self._episodes is not None
        try:
            request = json.loads(job.payload or b"{}")
            episode.seed = check_seed(request.get("seed") if isinstance(request, dict) else None)
            episode.resets += 1
            if not self._episodes.shared:  # the shared skill keeps no episode: its clients' seeds are theirs
                skill = self._episodes.skill_of(episode)
                _recover(skill)
                skill.reset(seed=episode.seed)
        except Exception as exc:
            self.stats.errors += 1
            _reply_error(job.query, f"reset failed: {exc}")
            return
        self.stats.resets += 1
        job.query.reply(self.keys.reset, b"{}")
        job.query.drop()

    def _infer(self, jobs: Sequence[Job]) -> None:
        """Decode each request, run them (batched where they share a skill that batches), answer each."""
        prepared = [p for p in (self._prepare(job, len(jobs)) for job in jobs) if p is not None]
        groups: dict[int, list[_Prepared]] = {}
        for item in prepared:
            groups.setdefault(id(item.skill), []).append(item)
        for group in groups.values():
            self._run(group)

    def _prepare(self, job: Job, batch_size: int) -> _Prepared | None:
        queue_ms = (time.monotonic_ns() - job.received_ns) / 1e6
        carrier: dict[str, str] = {
            key: str(job.attachment[key]) for key in ("traceparent", "tracestate") if key in job.attachment
        }
        span = tracer().start_span(
            semconv.SPAN_REMOTE_INFER,
            context=extract(carrier),
            attributes={
                semconv.ATTR_REMOTE_KEY: self.keys.infer,
                semconv.ATTR_REMOTE_QUEUE_MS: queue_ms,
                semconv.ATTR_REMOTE_REQUEST_BYTES: len(job.payload),
                semconv.ATTR_REMOTE_BATCH_SIZE: batch_size,
            },
        )
        assert self._episodes is not None
        try:
            episode = self._episodes.episode(job.client)
            try:
                request = request_from_fields(decode(job.payload), action_dims=len(self.meta.action_names))
            except WireFormatError as exc:
                raise WireFormatError(f"bad request: {exc}") from None
            if request.seed is None and episode.seed is not None:  # a client that sends its seed on reset only
                request = dataclasses.replace(request, seed=episode.seed)
            skill = self._episodes.skill_of(episode)
            _recover(skill)  # an earlier inference failed: try again from a clean state
        except Exception as exc:
            self._fail(job, span, exc)
            return None
        return _Prepared(job, request, skill, span, queue_ms)

    def _run(self, group: list[_Prepared]) -> None:
        """One inference for the group where its skill batches; one by one otherwise, or if the batch fails."""
        skill = group[0].skill
        started = time.perf_counter()
        if len(group) > 1:
            try:
                chunks = skill.step_chunks([item.request for item in group])
            except Exception as exc:  # one bad request must not fail the others: run them one by one
                _log.warning("a batch failed; running its requests one by one", error=str(exc), size=len(group))
                _recover(skill)
            else:
                infer_ms = (time.perf_counter() - started) * 1e3
                self._note_batch(len(group))
                for item, chunk in zip(group, chunks, strict=True):
                    self._answer(item, chunk, infer_ms)
                return
        for item in group:
            started = time.perf_counter()
            try:
                chunk = item.skill.step_chunk(item.request)
            except Exception as exc:
                self._fail(item.job, item.span, exc)
                _recover(item.skill)
                continue
            self._note_batch(1)
            self._answer(item, chunk, (time.perf_counter() - started) * 1e3)

    def _answer(self, item: _Prepared, chunk: np.ndarray, infer_ms: float) -> None:
        rows = np.asarray(chunk, dtype=np.float64)
        if rows.ndim != 2 or rows.shape[1] != len(self.meta.action_names):
            dims = len(self.meta.action_names)
            self._fail(
                item.job, item.span, ROSConfigError(f"the policy returned rows of shape {rows.shape}, not (n, {dims})")
            )
            return
        reply = encode(
            {"chunk": rows, "infer_ms": infer_ms, "queue_ms": item.queue_ms, "model_hash": self.meta.model_hash}
        )
        item.span.set_attributes({semconv.ATTR_REMOTE_OUTCOME: "ok", semconv.ATTR_REMOTE_REPLY_BYTES: len(reply)})
        item.span.end()
        assert self._episodes is not None
        self._episodes.episode(item.job.client).served += 1
        self.stats.served += 1
        item.job.query.reply(self.keys.infer, reply)
        item.job.query.drop()

    def _fail(self, job: Job, span: Span, exc: Exception) -> None:
        self.stats.errors += 1
        span.record_exception(exc)
        span.set_attribute(semconv.ATTR_REMOTE_OUTCOME, "error")
        span.end()
        _reply_error(job.query, f"{type(exc).__name__}: {exc}")

    def _note_batch(self, size: int) -> None:
        self.stats.batches += 1
        self.stats.largest_batch = max(self.stats.largest_batch, size)


def _client_id(attachment: dict[str, Any]) -> str:
    """The client's id from its attachment, cut to ``MAX_CLIENT_ID`` characters (a peer chooses it freely)."""
    return str(attachment.get("client", ""))[:MAX_CLIENT_ID]


def _recover(skill: RSkillBase) -> None:
    """Bring a skill whose last inference failed back to active, from a clean state."""
    if skill.last_error is not None:
        skill.recover()
        skill.activate()


def _payload(query: Any) -> bytes:
    payload = query.payload
    return b"" if payload is None else bytes(payload.to_bytes())


def _reply_error(query: Any, text: str) -> None:
    try:
        query.reply_err(text.encode("utf-8"))
    finally:
        query.drop()
