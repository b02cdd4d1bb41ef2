"""``PolicyService``: one policy served to many clients, whatever the transport.

A transport (Zenoh's :class:`~openral_remote.server.PolicyServer`, the openpi and vla-eval
websocket servers) turns what arrives into calls here and what comes back into replies:

* :meth:`PolicyService.infer` queues a chunk request of a client. Its ``request`` is a
  :class:`~openral_rskill.chunks.ChunkRequest`, or a function that decodes one, called on the
  worker thread (decoding a camera frame is work the transport's thread must not do).
* :meth:`PolicyService.reset` starts a new episode of a client, :meth:`PolicyService.leave`
  frees its episode (a closed connection).

Each submitted job gets **exactly one** answer: ``answer(Answer)`` (the chunk's rows and
timings) or ``error(text)``, called on the worker thread, or at once on the caller's thread
when it is refused (a full table or queue, a job superseded by its client's newer one), or
from :meth:`PolicyService.close`. A transport's callbacks must therefore be thread-safe and
must not block.

Behind it: each client has its episode (:mod:`openral_remote.episodes`, at most
``max_clients``), jobs wait in a bounded fair queue (:mod:`openral_remote.fair_queue`: latest
wins per client, clients in turn), and one worker thread infers, batching concurrent clients'
requests through :meth:`~openral_rskill.base.RSkillBase.step_chunks` where the skill can; a
request that fails (or fails its batch) never fails the others.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Self

import numpy as np
import structlog
from opentelemetry.trace import Span

from openral_core import ROSConfigError
from openral_observability import semconv, tracer
from openral_observability.propagation import extract
from openral_remote.admission import ServeLimits
from openral_remote.codec import WireFormatError
from openral_remote.episodes import ClientEpisode, EpisodeTable
from openral_remote.fair_queue import INFER, RESET, FairQueue, Job
from openral_remote.meta import PolicyMeta
from openral_rskill.base import RSkillBase
from openral_rskill.chunks import ChunkRequest

_log = structlog.get_logger(__name__)

ERROR_SUPERSEDED = "superseded"
ERROR_SHUTTING_DOWN = "shutting down"
ERROR_BUSY = "busy"
ERROR_FULL = "full"
MAX_CLIENT_ID = 64
"""Characters of a client's id kept: the episode table is keyed by it, and a peer may pick it."""


@dataclass(frozen=True)
class Answer:
    """A served chunk: ``rows`` ``(n, dims)`` float64, the inference's and the wait's milliseconds."""

    rows: np.ndarray
    infer_ms: float
    queue_ms: float


OnAnswer = Callable[[Answer], "int | None"]
"""Takes the chunk; may return the reply's size in bytes (recorded on the trace)."""
OnError = Callable[[str], None]
"""Takes a one-line error text."""
RequestSource = ChunkRequest | Callable[[], ChunkRequest]


@dataclass
class ServiceStats:
    """What a service has done since it started."""

    served: int = 0
    superseded: int = 0
    errors: int = 0
    resets: int = 0
    refused: int = 0
    """Requests turned away unread: over a limit, a camera the policy does not read, the queue or table full."""
    batches: int = 0
    largest_batch: int = 0


@dataclass
class _Ticket:
    """What a job carries through the queue (the fair queue's ``Job.query``)."""

    answer: OnAnswer | None
    error: OnError
    request: RequestSource | None = None
    seed: int | None = None
    trace: Mapping[str, str] = dataclasses.field(default_factory=dict)
    request_bytes: int = 0
    done: bool = False


@dataclass
class _Prepared:
    job: Job
    ticket: _Ticket
    request: ChunkRequest
    skill: RSkillBase
    span: Span
    queue_ms: float


class PolicyService:
    """Serves ``skill`` to the clients of one or more transports (:meth:`start` / :meth:`close`, or ``with``).

    Args:
        skill: The policy, unconfigured: the service configures, activates and shuts it down.
        meta: What the policy is (its action names size the chunks; ``warmup_ms`` is set on start).
        limits: Batching, clients and queue limits (request limits are the transport's to apply).
        factory: Makes another unconfigured instance of the skill for each further client of a
            skill that cannot be shared between episodes; without it such a skill serves one
            client at a time.
        name: Where it is served (the traces' ``remote.key``; the worker thread's name).
    """

    def __init__(
        self,
        skill: RSkillBase,
        *,
        meta: PolicyMeta,
        limits: ServeLimits | None = None,
        factory: Callable[[], RSkillBase] | None = None,
        name: str = "policy",
    ) -> None:
        self.skill = skill
        self.meta = meta
        self.limits = limits or ServeLimits()
        self.name = name
        self.stats = ServiceStats()
        self._factory = factory
        self._queue = FairQueue(self.limits.max_pending)
        self._episodes: EpisodeTable | None = None
        self._worker: threading.Thread | None = None
        self._lock = threading.Lock()
        self._waiting: dict[str, int] = {}
        """Jobs not answered yet, per client: a client that left is freed once its last is answered."""
        self._left: set[str] = set()
        self._closing = False

    def __enter__(self) -> PolicyService:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def clients(self) -> int:
        """Clients with an episode now."""
        return 0 if self._episodes is None else len(self._episodes)

    @property
    def batch_limit(self) -> int:
        """Requests one inference takes: ``max_batch`` where the skill is shared and batches, else 1."""
        shared = self._episodes is not None and self._episodes.shared
        return min(self.limits.max_batch, self.skill.batch_capacity()) if shared else 1

    def start(self) -> None:
        """Configure and warm the policy up, then start the worker (``meta.warmup_ms`` set)."""
        started = time.perf_counter()
        self.skill.configure()
        self.skill.activate()
        self.meta = self.meta.model_copy(update={"warmup_ms": (time.perf_counter() - started) * 1e3})
        self._episodes = EpisodeTable(self.skill, factory=self._factory, limits=self.limits)
        self._worker = threading.Thread(target=self._work, name=f"openral-serve-{self.name}"[:60], daemon=True)
        self._worker.start()

    def close(self) -> None:
        """Answer what is queued ``shutting down``, stop the worker, shut the policy down. Idempotent."""
        self._closing = True
        for job in self._queue.drain():
            self._settle(job, error=ERROR_SHUTTING_DOWN)
        if self._worker is not None:
            self._worker.join(timeout=5.0)
            self._worker = None
        if self._episodes is not None:
            self._episodes.retire_all()
        self.skill.shutdown()

    # -- what transports call (any thread) ---------------------------------------------------

    def infer(
        self,
        client: str,
        request: RequestSource,
        *,
        answer: OnAnswer,
        error: OnError,
        trace: Mapping[str, str] | None = None,
        request_bytes: int = 0,
    ) -> None:
        """Queue a chunk request of ``client``; ``answer`` or ``error`` is called once.

        Args:
            client: The client's id (cut to ``MAX_CLIENT_ID`` characters).
            request: The request, or a function decoding it on the worker thread (its
                :class:`WireFormatError` is answered ``bad request``).
            answer: Takes the chunk.
            error: Takes why there is none.
            trace: The request's W3C ``traceparent``/``tracestate``: the inference span's parent.
            request_bytes: The request's size, for the trace.
        """
        ticket = _Ticket(answer, error, request=request, trace=trace or {}, request_bytes=request_bytes)
        self._enqueue(Job(ticket, INFER, client=client[:MAX_CLIENT_ID]))

    def reset(self, client: str, seed: int | None, *, done: Callable[[], None], error: OnError) -> None:
        """Start a new episode of ``client`` (its seed: ``None`` for unseeded); ``done`` or ``error`` is called once."""

        def answered(_answer: Answer) -> None:
            done()

        self._enqueue(Job(_Ticket(answered, error, seed=seed), RESET, client=client[:MAX_CLIENT_ID]))

    def leave(self, client: str) -> None:
        """``client`` is gone: its episode is freed once the jobs it still has queued are answered."""
        client = client[:MAX_CLIENT_ID]
        with self._lock:
            if self._waiting.get(client):
                self._left.add(client)
                return
        if self._episodes is not None:
            self._episodes.release(client)

    def refuse(self, error: OnError, text: str) -> None:
        """Answer a request the transport refused unread (counted as refused)."""
        self.stats.refused += 1
        error(text)

    # -- admission --------------------------------------------------------------------------

    def _enqueue(self, job: Job) -> None:
        """Queue ``job`` for its client's episode; answer at once what it supersedes or displaces, or it if refused."""
        with self._lock:
            self._waiting[job.client] = self._waiting.get(job.client, 0) + 1
        episodes = self._episodes
        if episodes is None or not episodes.admit(job.client):
            self.stats.refused += 1
            self._settle(job, error=f"{ERROR_FULL}: the server has {self.limits.max_clients} clients under way")
            return
        job.established = episodes.established(job.client)
        admission = self._queue.put(job)
        for old in admission.superseded:
            self.stats.superseded += 1
            self._settle(old, error=ERROR_SUPERSEDED)
        for old in admission.displaced:
            self.stats.refused += 1
            self._settle(old, error=f"{ERROR_BUSY}: displaced by a robot under way")
        if not admission.accepted:
            if self._closing:
                self._settle(job, error=ERROR_SHUTTING_DOWN)
            else:
                self.stats.refused += 1
                self._settle(job, error=f"{ERROR_BUSY}: {self.limits.max_pending} requests are waiting")

    def _settle(self, job: Job, *, answer: Answer | None = None, error: str | None = None) -> int | None:
        """Answer ``job`` (once), then free its client's episode if it left and this was its last job."""
        ticket: _Ticket = job.query
        if ticket.done:
            return None
        ticket.done = True
        size: int | None = None
        try:
            if answer is not None and ticket.answer is not None:
                size = ticket.answer(answer)
            else:
                ticket.error(error or "no answer")
        except Exception as exc:  # a transport's callback must not stop the worker
            _log.warning("a reply could not be sent", client=job.client, error=str(exc))
        with self._lock:
            left = self._waiting.get(job.client, 1) - 1
            if left > 0:
                self._waiting[job.client] = left
                return size
            self._waiting.pop(job.client, None)
            gone = job.client in self._left
            self._left.discard(job.client)
        if gone and self._episodes is not None:
            self._episodes.release(job.client)
        return size

    # -- the worker -------------------------------------------------------------------------

    def _work(self) -> None:
        episodes = self._episodes
        assert episodes is not None
        batch_limit = self.batch_limit  # asked once: a model's batch dimension does not change
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
        ticket: _Ticket = job.query
        try:
            episode.seed = ticket.seed
            episode.resets += 1
            if not self._episodes.shared:  # the shared skill keeps no episode: its clients' seeds are theirs
                skill = self._episodes.skill_of(episode)
                _recover(skill)
                skill.reset(seed=episode.seed)
        except Exception as exc:
            self.stats.errors += 1
            self._settle(job, error=f"reset failed: {exc}")
            return
        self.stats.resets += 1
        self._settle(job, answer=Answer(np.zeros((0, 0)), 0.0, 0.0))

    def _infer(self, jobs: Sequence[Job]) -> None:
        """Decode each request, run them (batched where they share a skill that batches), answer each."""
        prepared = [p for p in (self._prepare(job, len(jobs)) for job in jobs) if p is not None]
        groups: dict[int, list[_Prepared]] = {}
        for item in prepared:
            groups.setdefault(id(item.skill), []).append(item)
        for group in groups.values():
            self._run(group)

    def _prepare(self, job: Job, batch_size: int) -> _Prepared | None:
        ticket: _Ticket = job.query
        queue_ms = (time.monotonic_ns() - job.received_ns) / 1e6
        span = tracer().start_span(
            semconv.SPAN_REMOTE_INFER,
            context=extract(dict(ticket.trace)),
            attributes={
                semconv.ATTR_REMOTE_KEY: self.name,
                semconv.ATTR_REMOTE_QUEUE_MS: queue_ms,
                semconv.ATTR_REMOTE_REQUEST_BYTES: ticket.request_bytes,
                semconv.ATTR_REMOTE_BATCH_SIZE: batch_size,
            },
        )
        assert self._episodes is not None
        try:
            episode = self._episodes.episode(job.client)
            source = ticket.request
            try:
                request = source() if callable(source) else source
            except WireFormatError as exc:
                raise WireFormatError(f"bad request: {exc}") from None
            assert isinstance(request, ChunkRequest)
            if request.seed is None and episode.seed is not None:  # a client that sends its seed on reset only
                request = dataclasses.replace(request, seed=episode.seed)
            skill = self._episodes.skill_of(episode)
            _recover(skill)  # an earlier inference failed: try again from a clean state
        except Exception as exc:
            self._fail(job, span, exc)
            return None
        return _Prepared(job, ticket, request, skill, span, queue_ms)

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
        dims = len(self.meta.action_names)
        if rows.ndim != 2 or rows.shape[1] != dims:
            error = ROSConfigError(f"the policy returned rows of shape {rows.shape}, not (n, {dims})")
            self._fail(item.job, item.span, error)
            return
        assert self._episodes is not None
        self._episodes.episode(item.job.client).served += 1
        self.stats.served += 1
        size = self._settle(item.job, answer=Answer(rows, infer_ms, item.queue_ms))
        item.span.set_attribute(semconv.ATTR_REMOTE_OUTCOME, "ok")
        if size is not None:
            item.span.set_attribute(semconv.ATTR_REMOTE_REPLY_BYTES, size)
        item.span.end()

    def _fail(self, job: Job, span: Span, exc: Exception) -> None:
        self.stats.errors += 1
        span.record_exception(exc)
        span.set_attribute(semconv.ATTR_REMOTE_OUTCOME, "error")
        span.end()
        self._settle(job, error=f"{type(exc).__name__}: {exc}")

    def _note_batch(self, size: int) -> None:
        self.stats.batches += 1
        self.stats.largest_batch = max(self.stats.largest_batch, size)


def _recover(skill: RSkillBase) -> None:
    """Bring a skill whose last inference failed back to active, from a clean state."""
    if skill.last_error is not None:
        skill.recover()
        skill.activate()


class ServiceTransport:
    """What every transport over a :class:`PolicyService` shares: a context manager, the policy's meta, the figures.

    A transport sets ``service`` in its constructor and implements ``start`` (warm the policy up,
    then listen) and ``close``.
    """

    service: PolicyService

    def start(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def meta(self) -> PolicyMeta:
        """What the policy is (with its warm-up time once started)."""
        return self.service.meta

    @property
    def stats(self) -> ServiceStats:
        """What the service has done since it started."""
        return self.service.stats

    @property
    def clients(self) -> int:
        """Clients with an episode now."""
        return self.service.clients


__all__ = [
    "ERROR_BUSY",
    "ERROR_FULL",
    "ERROR_SHUTTING_DOWN",
    "ERROR_SUPERSEDED",
    "MAX_CLIENT_ID",
    "Answer",
    "PolicyService",
    "ServiceStats",
    "ServiceTransport",
]
