"""``ChunkedExecutor``: a chunking policy's inference off the tick thread, its rows indexed by tick.

A policy that emits chunks of future actions takes longer than a tick to infer. The executor
keeps the tick thread from ever waiting on it:

* **The tick reads a buffer.** :meth:`ChunkedExecutor.step` returns this tick's action, or an
  explicit "no action" (starved, stop), in O(1). It never waits on the worker.
* **The worker owns the policy.** One thread runs inference and ``reset`` in the order they were
  asked for, so a reset never runs concurrently with inference. One request is in flight at a time.
* **Rows are indexed by tick.** A request carries the tick of its observation ``k``; row ``j``
  of its chunk is for tick ``k + j``. On the worker its rows are anchored as absolute targets at
  tick ``k`` (:mod:`openral_rskill.anchoring`); when it arrives it is placed in the tick-indexed
  :class:`~openral_rskill.chunk_buffer.ChunkBuffer` (rows for past ticks skipped, seams, a chunk
  with fewer than ``min_rows`` usable rows discarded and counted).
* **When to infer**: once the rows left fall to the recent p95 inference latency in ticks
  (warm-up excluded) plus ``margin_ticks``.
* **Starvation is explicit**: with no row for this tick the last target is held (counted); after
  ``max_starved_ticks`` in a row the decision is the fallback (a local skill) or a safe stop.
* **Deadlines, epochs**: a result later than ``deadline_ticks`` after its request is dropped by
  id; a reset starts a new epoch, and results of an older epoch are dropped. A policy whose
  inference raises ``TimeoutError`` (a remote server past its deadline) is counted late too.
* **A source that knows it is down** (``available`` returns ``False``: a remote policy's server
  is gone) is not asked; its buffered rows are dropped and the fallback decides from that very
  tick, without waiting out the starvation allowance.
* **Past commands**: for a policy that reads executed actions (``past_actions``), the runner
  hands back each command it actually sent, after the safety check (:meth:`ChunkedExecutor.sent`);
  the last ones are kept by tick (bounded) and each request carries those before its tick.
* **One trace**: each request's span starts on the tick that asks (a child of that tick) and ends
  when the chunk is settled; inference runs under it, so a remote server's span joins the trace.

Virtual latency (a simulation's): with ``virtual_delay`` the policy runs inline when asked and its
chunk becomes usable exactly ``virtual_delay(request)`` ticks later: the executor's effect on
success is then measured reproducibly, whatever the machine.

Every option is a field of :class:`~openral_core.execution.ExecutorConfig`, taken whole; what
comes from the skill (its chunk, reset, anchor, availability, identity) is given by
:meth:`ChunkedExecutor.for_skill`.
"""

from __future__ import annotations

import collections
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Final

import numpy as np
import structlog
from opentelemetry import trace
from opentelemetry.trace import Span

from openral_core import Action, ControlMode, ExecutorConfig, StarvationFallback, WorldState
from openral_observability import metrics, semconv, tracer
from openral_observability.deferred import TickTelemetry
from openral_rskill.anchoring import AbsoluteAnchor, Anchor, UnanchoredRows
from openral_rskill.base import RSkillBase
from openral_rskill.chunk_buffer import ChunkBuffer
from openral_rskill.chunks import ChunkRequest

_log = structlog.get_logger(__name__)

_LATENCY_WINDOW: Final = 50
"""Recent inference latencies (in ticks) the p95 is taken over."""


class Outcome(StrEnum):
    """What :meth:`ChunkedExecutor.step` decided for this tick."""

    ACTION = "action"
    """A row of a chunk, for this very tick."""
    HOLD = "hold"
    """No row for this tick: the last target, held (a starved tick)."""
    FALLBACK = "fallback"
    """Starved too long: the fallback skill should act."""
    STOP = "stop"
    """Starved too long: stop safely."""
    NONE = "none"
    """Nothing to send yet (no chunk has arrived and there is no target to hold)."""


@dataclass(frozen=True)
class Decision:
    """This tick's decision: an action (a chunk's row, or the held target) or why there is none."""

    outcome: Outcome
    action: Action | None = None
    chunk: int | None = None
    """The id of the request whose chunk the action's row came from (a held row keeps its chunk's)."""


@dataclass
class ExecutorStats:
    """Counters the runner reports (and telemetry counts as they happen)."""

    requests: int = 0
    chunks_used: int = 0
    chunks_discarded: int = 0
    results_late: int = 0
    results_stale_epoch: int = 0
    rows_skipped: int = 0
    starved_ticks: int = 0
    unavailable_ticks: int = 0
    """Ticks on which the policy's source said it was down (and the fallback decided)."""
    errors: int = 0
    stale_rows: int = 0
    """Rows sent on a tick other than the one they were computed for (``indexing: stale_start`` only)."""
    delays_ticks: collections.deque[int] = field(default_factory=lambda: collections.deque(maxlen=1000))
    """Delays of the most recent chunks used (bounded: a robot runs for days)."""


@dataclass
class _Request:
    request_id: int
    epoch: int
    obs_tick: int
    world: WorldState
    history: tuple[WorldState, ...] = ()
    prefix: np.ndarray | None = None
    past: tuple[tuple[int, np.ndarray], ...] = ()
    """The commands sent before ``obs_tick``, oldest first, with their ticks."""
    expected_delay: int = 0
    ready_tick: int | None = None
    """Virtual latency: the tick from which the chunk may be used."""
    rows: np.ndarray | None = None
    targets: np.ndarray | None = None
    """The rows anchored at the observation, computed where the rows were (off the tick thread)."""
    error: BaseException | None = None
    span: Span | None = None
    """From the request to the chunk's settling; inference runs under it."""


def _no_reset() -> None:
    return


_NO_RESET: Final = _no_reset

PolicyFn = Callable[[ChunkRequest], np.ndarray]
"""Inference: the request (observation, history, prefix) in, a ``(rows, dims)`` chunk out. Runs on the worker only."""


class ChunkedExecutor:
    """Runs ``infer`` on a worker and serves its chunks' rows tick by tick.

    Args:
        infer: The policy's inference (on the worker thread, or inline under virtual latency).
        config: The executor's settings, whole (seams, margins, deadlines, starvation, indexing).
        action_names: Names of the action's dimensions (the ``Action``'s joint names).
        reset: The policy's reset (on the worker, between inferences).
        anchor: How rows become targets and targets commands (absolute by default).
        available: Whether the policy's source can be asked now (a remote server's liveliness);
            ``None``: always. Called once per tick on the tick thread, so it must be O(1).
        observation_steps: Observations each request carries, the current one included: the
            executor keeps the earlier ticks' (references, O(1) per tick) for policies that read a history.
        past_actions: Commands sent before a request's tick that it carries (the runner hands
            each one to :meth:`sent`); 0: none are kept.
        skill_id: Put on the actions.
        control_mode: Put on the actions.
        virtual_delay: Simulation only: ticks from request to use, per request index in the episode
            (a public attribute: a simulation sets each episode's).
    """

    def __init__(
        self,
        infer: PolicyFn,
        config: ExecutorConfig | None = None,
        *,
        action_names: Sequence[str],
        reset: Callable[[], None] | None = None,
        anchor: Anchor | None = None,
        available: Callable[[], bool] | None = None,
        observation_steps: int = 1,
        past_actions: int = 0,
        skill_id: str | None = None,
        control_mode: ControlMode = ControlMode.JOINT_POSITION,
        virtual_delay: Callable[[int], int] | None = None,
    ) -> None:
        config = config or ExecutorConfig()
        anchor = anchor or AbsoluteAnchor()
        if isinstance(anchor, UnanchoredRows) and config.indexing != "stale_start":
            _log.warning(
                "the policy's rows cannot be anchored at their observation: each chunk runs from its first row "
                "when it arrives (stale start), however late",
                skill=skill_id,
            )
            config = config.model_copy(update={"indexing": "stale_start"})
        self.config = config
        self._infer = infer
        self._reset_policy = reset
        self.action_names = list(action_names)
        self.anchor: Anchor = AbsoluteAnchor() if config.indexing == "stale_start" else anchor
        self.virtual_delay = virtual_delay
        self.skill_id = skill_id
        self.control_mode = control_mode
        self._available = available
        self._history: collections.deque[WorldState] = collections.deque(maxlen=max(0, observation_steps - 1))
        self._past: collections.deque[tuple[int, np.ndarray]] = collections.deque(maxlen=max(0, past_actions))
        self._buffer = ChunkBuffer(len(self.action_names), config)
        self.stats = ExecutorStats()
        self._epoch = 0
        self._next_id = 0
        self._held: np.ndarray | None = None
        self._buffered_chunk: int | None = None
        """The request whose chunk the buffer's rows are from: placing one replaces every row from its tick on."""
        self._held_chunk: int | None = None
        self._row_offset = 0
        """Ticks between the tick a buffered row is served on and the tick it was computed for."""
        self._starved_in_row = 0
        self._in_flight: _Request | None = None
        self._latencies: collections.deque[int] = collections.deque(maxlen=_LATENCY_WINDOW)
        self._done: collections.deque[_Request] = collections.deque()
        self._jobs: collections.deque[_Request | Callable[[], None]] = collections.deque()
        self._epoch_first_id = 0
        self._wake = threading.Condition()
        self._closed = False
        self._abandoned: set[int] = set()
        self._p95 = 1
        self._telemetry: TickTelemetry | None = None
        self._thread: threading.Thread | None = None
        if virtual_delay is None:
            self._thread = threading.Thread(target=self._work, name="openral-chunk-worker", daemon=True)
            self._thread.start()

    @classmethod
    def for_skill(
        cls,
        skill: RSkillBase,
        config: ExecutorConfig | None = None,
        *,
        action_names: Sequence[str],
        virtual_delay: Callable[[int], int] | None = None,
    ) -> ChunkedExecutor:
        """The executor of a chunking skill: its :meth:`~RSkillBase.step_chunk` runs on the worker.

        The skill gives its reset, anchor, availability, observation history and identity; under
        ``virtual_delay`` it runs inline when asked.
        """
        info = skill.info
        return cls(
            skill.step_chunk,
            config,
            action_names=action_names,
            reset=skill.reset,
            anchor=skill.action_anchor(),
            available=skill.available,
            observation_steps=info.observation_steps,
            past_actions=info.past_actions,
            skill_id=info.skill_id,
            control_mode=info.control_mode,
            virtual_delay=virtual_delay,
        )

    # -- the tick thread -------------------------------------------------------------------

    def step(self, tick_idx: int, world: WorldState, telemetry: TickTelemetry | None = None) -> Decision:
        """This tick's decision, in O(1): take in arrived chunks, serve the row for ``tick_idx``, maybe ask for more.

        Args:
            telemetry: The runner's tick telemetry: chunk spans become children of the tick,
                recorded off the tick thread. Without it they go to the tracer directly.
        """
        self._telemetry = telemetry
        self._take_arrivals(tick_idx)
        history = self._history
        if self._available is not None and not self._available():
            if history.maxlen:
                history.append(world)
            return self._unavailable(world)
        self._maybe_request(tick_idx, world)
        if history.maxlen:
            history.append(world)
        if self.virtual_delay is not None and self._done:
            self._take_arrivals(tick_idx)  # a virtual delay of 0: this tick's own chunk
        row = self._buffer.row_for(tick_idx)
        if row is not None:
            self._starved_in_row = 0
            self._held = row
            self._held_chunk = chunk = self._buffered_chunk
            if self._row_offset:
                self.stats.stale_rows += 1
            return Decision(Outcome.ACTION, self._action(self.anchor.to_command(row, world), world), chunk)
        if self._held is None:
            return Decision(Outcome.NONE)
        self._starved_in_row += 1
        self.stats.starved_ticks += 1
        self._count(semconv.METRIC_EXECUTOR_STARVED_TICKS)
        fallback = self.config.fallback
        if self._starved_in_row > self.config.max_starved_ticks and fallback is not StarvationFallback.HOLD:
            return Decision(Outcome.FALLBACK if fallback is StarvationFallback.SKILL else Outcome.STOP)
        return Decision(Outcome.HOLD, self._action(self.anchor.to_command(self._held, world), world), self._held_chunk)

    def sent(self, tick_idx: int, command: Sequence[float]) -> None:
        """The command the robot was sent on ``tick_idx``, after the safety check: kept for requests that read the past.

        Called by the runner on the tick thread, after sending; O(1), and nothing at all when the
        policy reads no past.
        """
        if self._past.maxlen:
            self._past.append((tick_idx, np.asarray(command, dtype=np.float64)))

    def _unavailable(self, world: WorldState) -> Decision:
        """The source is down: its rows are dropped and the fallback decides now."""
        self._buffer.clear()
        self.stats.unavailable_ticks += 1
        self._count(semconv.METRIC_EXECUTOR_UNAVAILABLE_TICKS)
        # Past the starvation allowance: once the source is back, the fallback acts until a row arrives.
        self._starved_in_row = self.config.max_starved_ticks + 1
        fallback = self.config.fallback
        if fallback is StarvationFallback.SKILL:
            return Decision(Outcome.FALLBACK)
        if fallback is StarvationFallback.STOP:
            return Decision(Outcome.STOP)
        if self._held is None:
            return Decision(Outcome.NONE)
        return Decision(Outcome.HOLD, self._action(self.anchor.to_command(self._held, world), world), self._held_chunk)

    @property
    def fallback_active(self) -> bool:
        """Starved past the allowance with ``fallback: skill``: the fallback skill acts until a row arrives."""
        return self._starved_in_row > self.config.max_starved_ticks and self.config.fallback is StarvationFallback.SKILL

    def reset(self, run: Callable[[], None] | None = None) -> None:
        """A new episode: drop every row and in-flight result (a new epoch) and reset the policy on the worker.

        Args:
            run: The reset to run on the worker instead of the one given at construction (a
                simulation's, with the episode's seed).
        """
        self._epoch += 1
        self._epoch_first_id = self._next_id
        reset = run or self._reset_policy
        self._buffer.clear()
        self._held = None
        self._row_offset = 0
        self._starved_in_row = 0
        self._in_flight = None
        self._history.clear()  # a new episode's first request repeats its own first observation
        self._past.clear()  # and reads no command of the episode before
        if self.virtual_delay is not None:
            # A simulated episode starts from the latency it will see (its first request's virtual
            # delay) and learns afresh from there: what an episode does depends on its seed alone,
            # not on which episodes the same process ran before it.
            self._latencies.clear()
            self._p95 = max(0, int(self.virtual_delay(0)))
            if reset is not None:
                reset()
            return
        with self._wake:
            self._jobs.append(reset if reset is not None else _NO_RESET)
            self._wake.notify()

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the worker (a hung inference is abandoned after ``timeout_s``: the thread is a daemon)."""
        with self._wake:
            self._closed = True
            self._wake.notify()
        if self._thread is not None:
            self._thread.join(timeout_s)

    @property
    def results_waiting(self) -> int:
        """Results the worker has finished that the next :meth:`step` will take in."""
        return len(self._done)

    @property
    def in_flight(self) -> bool:
        """Whether a request is out (and not given up on)."""
        return self._in_flight is not None

    @property
    def rows_left(self) -> int:
        """Rows buffered for the current tick and after it (as of the last step)."""
        return len(self._buffer)

    def latency_ticks_p95(self) -> int:
        """The recent p95 inference latency in ticks (1 before any measurement)."""
        return self._p95

    # -- internals (tick thread) -----------------------------------------------------------

    def _maybe_request(self, tick_idx: int, world: WorldState) -> None:
        if self._in_flight is not None or self._abandoned:
            return  # one request at a time, a given-up one included: it still occupies the worker
        if self._buffer.ahead(tick_idx) > self._p95 + self.config.margin_ticks:
            return
        request = _Request(
            self._next_id, self._epoch, tick_idx, world, history=tuple(self._history), past=tuple(self._past)
        )
        self._next_id += 1
        self._in_flight = request
        self.stats.requests += 1
        attributes = {semconv.ATTR_EXECUTOR_REQUEST_ID: request.request_id, semconv.ATTR_EXECUTOR_OBS_TICK: tick_idx}
        telemetry = self._telemetry
        request.span = (
            telemetry.start_lasting_span(semconv.SPAN_EXECUTOR_CHUNK, attributes)
            if telemetry is not None
            else tracer().start_span(semconv.SPAN_EXECUTOR_CHUNK, attributes=attributes)
        )
        if self.virtual_delay is not None:
            index_in_epoch = request.request_id - self._epoch_first_id
            request.ready_tick = tick_idx + max(0, int(self.virtual_delay(index_in_epoch)))
            request.expected_delay = request.ready_tick - tick_idx
            request.prefix = self._buffer.rows_from(tick_idx)[: request.expected_delay]
            self._run(request)
            return
        request.expected_delay = self.latency_ticks_p95()
        request.prefix = self._buffer.rows_from(tick_idx)[: request.expected_delay]  # what runs while it infers
        with self._wake:
            self._jobs.append(request)
            self._wake.notify()

    def _take_arrivals(self, tick_idx: int) -> None:
        while self._done:
            request = self._done[0]
            if request.epoch == self._epoch and request.ready_tick is not None and request.ready_tick > tick_idx:
                # Virtual latency: not usable yet (a given-up request keeps the worker until then, as
                # on a robot). One of an episode before is dropped at once: an episode's course
                # depends on its own seed, never on how the one before it ended.
                return
            self._done.popleft()
            if request.request_id in self._abandoned:
                self._abandoned.discard(request.request_id)  # given up on at its deadline: dropped by id
                continue
            if request is self._in_flight:
                self._in_flight = None
            self._integrate(request, tick_idx)
        in_flight = self._in_flight
        if in_flight is not None and tick_idx - in_flight.obs_tick > self.config.deadline_ticks:
            # Past its deadline: give up on it (another request may go out); if it ever arrives it is dropped.
            self.stats.results_late += 1
            self._abandoned.add(in_flight.request_id)
            self._in_flight = None
            self._chunk_span(in_flight, tick_idx, {semconv.ATTR_EXECUTOR_DISCARDED: "late"})

    def _integrate(self, request: _Request, tick_idx: int) -> None:
        delay = tick_idx - request.obs_tick
        reason = self._refusal(request, delay)
        if reason is not None:
            self._chunk_span(request, tick_idx, {semconv.ATTR_EXECUTOR_DISCARDED: reason})
            return
        first = self._epoch_first_id if self.virtual_delay is not None else 0
        if request.request_id - first >= self.config.warmup_requests:
            self._latencies.append(delay)
            ordered = sorted(self._latencies)  # a few dozen ints: cheaper than numpy on the tick thread
            self._p95 = ordered[math.ceil(0.95 * len(ordered)) - 1]
        self.stats.delays_ticks.append(delay)
        assert request.targets is not None
        placed = self._buffer.place(request.targets, obs_tick=request.obs_tick, tick=tick_idx)
        self.stats.rows_skipped += placed.skipped
        outcome: dict[str, Any] = {
            semconv.ATTR_EXECUTOR_ROWS_SKIPPED: placed.skipped,
            semconv.ATTR_EXECUTOR_ROWS_USED: placed.used,
        }
        if placed.refused:
            self.stats.chunks_discarded += 1
            outcome[semconv.ATTR_EXECUTOR_DISCARDED] = "too_few_rows"
        else:
            self.stats.chunks_used += 1
            self._buffered_chunk = request.request_id
            # Tick-indexed rows are served on their own tick; a stale start serves row 0 on arrival.
            self._row_offset = delay if self._buffer.stale_start else 0
        self._chunk_span(request, tick_idx, outcome)

    def _chunk_span(self, request: _Request, tick_idx: int, outcome: dict[str, Any]) -> None:
        """End the request's span and record its metrics when it is settled (used, discarded or given up on)."""
        delay = tick_idx - request.obs_tick
        span = request.span
        if span is not None:
            request.span = None
            span.set_attributes({semconv.ATTR_EXECUTOR_READY_TICK: tick_idx, semconv.ATTR_EXECUTOR_DELAY_TICKS: delay})
            span.set_attributes(outcome)
            if outcome.get(semconv.ATTR_EXECUTOR_DISCARDED) in ("error", "late") and request.error is not None:
                span.record_exception(request.error)
            telemetry = self._telemetry
            if telemetry is not None:
                telemetry.end_lasting_span(span)
            else:
                span.end()
        reason = outcome.get(semconv.ATTR_EXECUTOR_DISCARDED)
        if reason is None:
            self._record(semconv.METRIC_EXECUTOR_DELAY, float(delay))
        else:
            self._count(semconv.METRIC_EXECUTOR_DISCARDED, {semconv.ATTR_EXECUTOR_DISCARDED: reason})

    @staticmethod
    def _count(name: str, attributes: dict[str, Any] | None = None) -> None:
        metrics.add(name, 1, attributes)

    @staticmethod
    def _record(name: str, value: float) -> None:
        metrics.histogram(name, unit="{tick}").record(value)

    def _refusal(self, request: _Request, delay: int) -> str | None:
        if request.epoch != self._epoch:
            self.stats.results_stale_epoch += 1
            return "stale_epoch"
        if isinstance(request.error, TimeoutError):
            self.stats.results_late += 1
            return "late"
        if request.error is not None:
            self.stats.errors += 1
            _log.warning("chunk inference failed", error=str(request.error), request=request.request_id)
            return "error"
        if delay > self.config.deadline_ticks:
            self.stats.results_late += 1
            return "late"
        rows = request.rows
        if rows is None or rows.ndim != 2 or rows.shape[1] != len(self.action_names):
            self.stats.errors += 1
            return "bad_shape"
        return None

    def _action(self, row: np.ndarray, world: WorldState) -> Action:
        # Built without validation (the shape is the executor's own): this runs every tick.
        return Action.trusted(
            control_mode=self.control_mode,
            joint_names=self.action_names,
            targets=[row.tolist()],
            stamp_ns=world.stamp_ns,
            skill_id=self.skill_id,
        )

    # -- the worker ------------------------------------------------------------------------

    def _prepare(self, request: _Request, output: np.ndarray) -> None:
        """Keep a result's rows and anchor them at its observation, so the tick only indexes them."""
        rows = np.asarray(output, dtype=np.float64)
        request.rows = rows
        if rows.ndim == 2 and rows.shape[1] == len(self.action_names):
            request.targets = self.anchor.to_targets(rows, request.world)

    def _work(self) -> None:
        while True:
            with self._wake:
                while not self._jobs and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                job = self._jobs.popleft()
            if not isinstance(job, _Request):
                try:
                    job()
                except Exception as exc:
                    _log.warning("policy reset failed", error=str(exc))
                continue
            assert isinstance(job, _Request)
            self._run(job)

    def _run(self, request: _Request) -> None:
        """Infer under the request's span (so spans the policy makes, a remote server's too, are its children)."""
        dims = len(self.action_names)
        past = request.past
        asked = ChunkRequest(
            request.world,
            obs_tick=request.obs_tick,
            history=request.history,
            prefix=request.prefix if request.prefix is not None else np.zeros((0, dims)),
            inference_delay=request.expected_delay,
            past=np.stack([command for _, command in past]) if past else np.zeros((0, dims)),
            past_ticks=tuple(tick for tick, _ in past),
        )
        try:
            if request.span is None:
                self._prepare(request, self._infer(asked))
            else:
                with trace.use_span(request.span, record_exception=False, set_status_on_exception=False):
                    self._prepare(request, self._infer(asked))
        except Exception as exc:
            request.error = exc
        self._done.append(request)  # deque.append is atomic: the tick thread takes it on its next step
