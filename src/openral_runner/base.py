"""``InferenceRunnerBase``: cadence, deadline policy, the tick span, and honest run statistics.

Subclasses implement ``_tick_impl``, which writes its phases into the tick's ``TickContext`` (every
runner around a skill runs the one in :mod:`openral_runner.skill_runner`); the base owns everything
around one tick and builds its ``TickResult`` once:

* **Absolute schedule.** Slot ``k`` starts at ``t0 + k / rate_hz``. After an overrun the next
  tick starts at the next future slot boundary; skipped slots are counted, phase is kept, and
  there is never a catch-up burst.
* **Deadline policy before actuation.** The tick calls ``_deadline_allows_send()`` after
  safety and before it acts: ``warn`` sends and counts, ``drop`` withholds the late
  action, ``raise`` withholds it, stops the loop and raises ``ROSDeadlineMissed`` carrying
  the partial ``RunResult``.
* **Faults as policy.** Ticks withheld for a fault (stale required sensor, failed state read,
  skill error, HAL error) are counted; after ``max_consecutive_failures`` in a row the loop
  stops with ``stop_reason="faults"``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from typing import Any, Final

import structlog
from opentelemetry import context, trace
from opentelemetry.trace import Span, Status, StatusCode

from openral_core import (
    DeadlineOverrunPolicy,
    GarbageCollection,
    ROSConfigError,
    ROSDeadlineMissed,
    ROSRuntimeError,
    ROSStopRequested,
    RunResult,
    StopReason,
    TickResult,
    WorldState,
)
from openral_observability import metrics, semconv, trace_id_hex, traceparent
from openral_observability.deferred import TickTelemetry
from openral_observability.observer import StartableObserver, ThumbnailSource, ThumbnailSubscriber, TickObserver
from openral_observability.tick_recorder import TickRecorder
from openral_runner.clock import Clock, SystemClock
from openral_runner.gc_policy import BetweenTicksCollector
from openral_runner.stats import RunStats
from openral_runner.tick_context import TickContext
from openral_runner.tick_span import tick_span_attributes

_log = structlog.get_logger(__name__)

_RECENT_TICKS: Final = 4096
_PER_RUN_STOPS: Final = frozenset({StopReason.STOP_REQUESTED, StopReason.SKILL_DONE})
"""Stop reasons that end one ``run()`` only; signals, faults and e-stops stay until ``deactivate()``."""


class InferenceRunnerBase(ABC):
    """Shared loop for hardware and sim runners.

    Args:
        rate_hz: Tick rate; must be positive.
        deadline_overrun_policy: What to do with an action ready after its slot ends.
        runner_name: Name reported in results and logs.
        latency_budget_ms: Optional per-tick budget; ticks longer than it are counted.
        clock: Scheduling clock; a fake clock makes tests deterministic.
        skill_id: Reported in results and as the ``skill.id`` metric label.
        max_consecutive_failures: Faulted ticks in a row that end the run safely.
        garbage_collection: When Python's garbage collector may run during ``run()``; by default
            only in the idle time between ticks (:mod:`openral_runner.gc_policy`).
        free_running: Start each tick as soon as the previous one ends, with no slots and no
            deadline (a simulation evaluated as fast as it steps); ``rate_hz`` then only names the
            control rate.
    """

    def __init__(
        self,
        *,
        rate_hz: float = 30.0,
        deadline_overrun_policy: DeadlineOverrunPolicy = DeadlineOverrunPolicy.WARN,
        runner_name: str = "inference_runner",
        latency_budget_ms: float | None = None,
        clock: Clock | None = None,
        skill_id: str | None = None,
        max_consecutive_failures: int = 5,
        garbage_collection: GarbageCollection = GarbageCollection.BETWEEN_TICKS,
        free_running: bool = False,
    ) -> None:
        if not rate_hz > 0:
            raise ROSConfigError(f"must be positive, got {rate_hz}", field="rate_hz")
        if max_consecutive_failures < 1:
            raise ROSConfigError("must be at least 1", field="faults.max_consecutive_failures")
        self.rate_hz = float(rate_hz)
        self.period_s = 1.0 / self.rate_hz
        self.deadline_overrun_policy = DeadlineOverrunPolicy(deadline_overrun_policy)
        self.runner_name = runner_name
        self.latency_budget_ms = latency_budget_ms
        self.skill_id = skill_id
        self.max_consecutive_failures = max_consecutive_failures
        self.garbage_collection = GarbageCollection(garbage_collection)
        self.free_running = free_running
        self._clock: Clock = clock or SystemClock()
        self._active = False
        self._tick_idx = 0
        self._stop_reason: StopReason | None = None
        self._tick = TickContext(0, 0.0, 0.0)
        self._spans_current = False
        """Whether this tick's spans are made current (not under the API's no-op provider)."""
        self._raise_pending = False
        self._metric_attrs = {semconv.ATTR_SKILL_ID: skill_id or runner_name}
        # Each tick's spans and metric samples are recorded as data and exported by a worker
        # thread under an SDK provider (``openral_observability.deferred``); with the API's no-op
        # providers they are the API's near-free no-ops. (Telemetry only: a dataset recorder is an observer.)
        self._telemetry_recorder = TickRecorder()
        self._telemetry = TickTelemetry(trace.INVALID_SPAN, defer_metrics=False)
        self._last_late_log_s = float("-inf")
        self._late_since_log = 0
        self.metadata: dict[str, Any] = {}
        self.recent_ticks: deque[TickResult] = deque(maxlen=_RECENT_TICKS)
        self.observers: list[TickObserver] = []
        self._stats = RunStats()
        self._reset_counters()

    # -- lifecycle -----------------------------------------------------------------------

    @property
    def is_active(self) -> bool:
        """True between ``activate()`` and ``deactivate()``."""
        return self._active

    def activate(self) -> None:
        """Reset the tick counter, start the observers and the telemetry worker, and mark the runner ready to tick.

        How ticks are recorded is decided here, once, from the installed OpenTelemetry providers
        (SDK ones: deferred to the worker; the API's no-op ones: recorded directly, for nothing).
        """
        self._tick_idx = 0
        for observer in self.observers:
            if isinstance(observer, StartableObserver):
                observer.start()  # what building them left closed: ports, sessions
        for source in self.observers:
            if isinstance(source, ThumbnailSource):
                for viewer in self.observers:
                    if isinstance(viewer, ThumbnailSubscriber):
                        source.subscribe(viewer.on_thumbnail)  # one JPEG encode for every viewer
        self._telemetry_recorder.activate()
        self._active = True

    def deactivate(self) -> None:
        """Stop ticking and flush the telemetry worker; a pending stop request is cleared. Idempotent."""
        self._active = False
        self._stop_reason = None
        self._telemetry_recorder.deactivate()

    def flush_telemetry(self, timeout_s: float = 10.0) -> bool:
        """Wait until the spans and metric samples of every tick so far are handed to the SDK.

        Returns:
            ``False`` if the worker did not catch up within ``timeout_s``.
        """
        return self._telemetry_recorder.worker.flush(timeout_s)

    @property
    def telemetry_dropped(self) -> int:
        """Ticks whose deferred telemetry was dropped because the worker fell behind."""
        return self._telemetry_recorder.worker.dropped

    def request_stop(self, reason: StopReason | str = StopReason.STOP_REQUESTED) -> None:
        """Ask ``run()`` to finish the current tick and return. Safe from signal handlers and threads.

        A request made before ``run()`` (during ``activate()``, say) is kept: start-up rolls back
        and ``run()`` returns at once. A plain stop request or the skill's "done" ends that one
        run, and the next ``run()`` (the next episode) ticks again; a signal, fault or e-stop
        stays until ``deactivate()``.
        """
        if self._stop_reason is None:
            self._stop_reason = StopReason(reason)

    @property
    def stop_requested(self) -> StopReason | None:
        """The pending stop reason, ``None`` when nobody asked the runner to stop."""
        return self._stop_reason

    def _check_stop(self) -> None:
        """Raise if a stop was requested: called between start-up steps so they roll back.

        Raises:
            ROSStopRequested: Carrying the stop reason.
        """
        reason = self._stop_reason
        if reason is not None:
            raise ROSStopRequested(f"{self.runner_name}: stop requested during start-up ({reason})", reason=reason)

    @abstractmethod
    def _tick_impl(self, tick: TickContext) -> None:
        """Run one tick's phases, writing what they learn into ``tick``.

        Call ``_deadline_allows_send()`` right before actuating; the base builds the
        ``TickResult`` from ``tick`` when this returns.
        """

    def _schedule_origin(self) -> float:
        """When slot 0 of ``run()`` starts (scheduling clock); subclasses may choose a phase. Now by default."""
        return self._clock.now()

    def _on_missed_slots(self, skipped: int) -> None:
        """Subclass hook: the last tick overran and ``skipped`` slots passed without a tick. Nothing by default.

        A simulation paced by the wall clock steps its world through them (as a robot keeps
        moving while its controller is late).
        """
        return

    def _should_terminate(self) -> bool:
        """Subclass hook consulted after each tick; ``True`` ends ``run()`` (``stop_reason="terminated"``)."""
        return False

    def episode_start(self, task_string: str) -> int:
        """Open an explicit episode boundary; runners that support episodes override this."""
        raise NotImplementedError(f"{type(self).__name__} has no explicit episodes")

    def episode_end(self, *, success: bool, keep: bool = True) -> None:
        """Close the episode opened by ``episode_start``; ``keep=False`` throws it away (a recorder discards it)."""
        raise NotImplementedError(f"{type(self).__name__} has no explicit episodes")

    # -- one tick ------------------------------------------------------------------------

    def tick(self) -> TickResult:
        """Run one tick now, with a deadline one period away; no cadence is enforced.

        Raises:
            ROSDeadlineMissed: Under the ``raise`` policy, when the tick was late.
        """
        self._require_active()
        tick = self._next_tick(0.0, 0.0)
        tick.start_s = self._clock.now()
        tick.deadline_s = tick.start_s + self.period_s
        return self._run_tick(tick)

    def _next_tick(self, start_s: float, deadline_s: float) -> TickContext:
        """The context of the next tick, made ahead of its slot (in the idle time before it)."""
        tick = TickContext(self._tick_idx, start_s, deadline_s)
        self._tick_idx += 1
        return tick

    def _run_tick(self, tick: TickContext, *, slot_start_s: float | None = None) -> TickResult:
        """Run the tick ``tick`` describes; its result is built once the tick is over.

        With ``slot_start_s`` the tick is prepared now, in the idle time before its slot, and
        starts when the slot does (``tick.start_s`` is set then); without it, it starts at
        ``tick.start_s``.
        """
        telemetry_recorder = self._telemetry_recorder
        telemetry = telemetry_recorder.begin() if slot_start_s is not None and telemetry_recorder.begins_ahead else None
        self._tick = tick
        self._raise_pending = False
        if slot_start_s is not None:
            self._clock.sleep_until(slot_start_s)
            tick.start_s = self._clock.now()
        # From here to the action, only the tick: its bookkeeping waits until it is over.
        if telemetry is None:
            telemetry = telemetry_recorder.begin()
        else:
            telemetry.restart()
        worker = telemetry_recorder.worker
        worker.busy = True
        idx = tick.tick_idx
        start_s = tick.start_s
        self._telemetry = telemetry
        span = telemetry.span
        # Current for whatever the phases start (a skill's own spans); under the API's no-op
        # provider there is nothing to parent, and the attach is skipped.
        self._spans_current = telemetry.parents_spans
        token = context.attach(trace.set_span_in_context(span)) if self._spans_current else None
        tick_attributes: dict[str, Any] | None = None
        try:
            self._tick_impl(tick)
            if not tick.deadline_checked:
                self._deadline_allows_send()
            tick_ms = (self._clock.now() - start_s) * 1e3
            result = tick.result(tick_ms=tick_ms, trace_context=traceparent(span) if token is not None else None)
            tick_attributes = self._account(result, span)
            if self.observers:
                self._notify(result, tick.world)
            if self._raise_pending:
                error = ROSDeadlineMissed(
                    f"tick {idx} was {tick.lateness_ms:.2f} ms past its deadline "
                    f"(policy raise): action withheld, robot holding",
                    tick_result=result,
                )
                span.record_exception(error)
                span.set_status(Status(StatusCode.ERROR, "deadline missed"))
                raise error
        finally:
            if token is not None:
                context.detach(token)
            telemetry_recorder.end(telemetry, tick_attributes)
            worker.busy = False
        return result

    def _deadline_allows_send(self) -> bool:
        """Apply the deadline policy now; ``False`` means withhold the action.

        Call once per tick, after safety and immediately before actuating.
        """
        tick = self._tick
        tick.deadline_checked = True
        late_s = self._clock.now() - tick.deadline_s
        if late_s <= 0.0:
            return True
        tick.lateness_ms = late_s * 1e3
        self._stats.deadline_misses += 1
        metrics.add(semconv.METRIC_DEADLINE_MISSES, 1, self._metric_attrs)
        self._telemetry.span.add_event(
            semconv.EVENT_DEADLINE_MISSED,
            {
                semconv.ATTR_LATENESS_MS: tick.lateness_ms,
                semconv.ATTR_DEADLINE_POLICY: self.deadline_overrun_policy.value,
            },
        )
        self._log_late()
        if self.deadline_overrun_policy is DeadlineOverrunPolicy.WARN:
            return True
        if self.deadline_overrun_policy is DeadlineOverrunPolicy.RAISE:
            self._raise_pending = True
        return False

    def _notify(self, result: TickResult, world: WorldState | None) -> None:
        for observer in list(self.observers):
            self._tell(observer, observer.on_tick, result, world)

    def _tell(self, observer: TickObserver, call: Callable[..., None], *args: Any, **kwargs: Any) -> None:
        """Call one observer; one that raises is logged and detached (it must never stop the robot)."""
        try:
            call(*args, **kwargs)
        except Exception as exc:
            _log.error("tick observer failed; detaching it", observer=type(observer).__name__, error=str(exc))
            if observer in self.observers:
                self.observers.remove(observer)

    def _log_late(self) -> None:
        """Log deadline misses at most once a second, with the count since the last line."""
        self._late_since_log += 1
        now = self._clock.now()
        if now - self._last_late_log_s >= 1.0:
            _log.warning(
                "tick late",
                lateness_ms=round(self._tick.lateness_ms, 3),
                policy=self.deadline_overrun_policy.value,
                late_ticks_since_last_report=self._late_since_log,
            )
            self._last_late_log_s = now
            self._late_since_log = 0

    def _account(self, result: TickResult, span: Span) -> dict[str, Any] | None:
        """Count the tick and report it as metrics; returns the tick span's attributes when it is recorded."""
        stats = self._stats
        over_budget = self.latency_budget_ms is not None and result.tick_ms > self.latency_budget_ms
        stats.count(result, over_budget=over_budget)
        reason = result.withheld_reason
        if reason is not None:
            metrics.add(
                semconv.METRIC_ACTIONS_WITHHELD, 1, {**self._metric_attrs, semconv.ATTR_WITHHELD_REASON: reason}
            )
            if stats.consecutive_failures >= self.max_consecutive_failures:
                _log.error(
                    "stopping: too many consecutive failed ticks",
                    failures=stats.consecutive_failures,
                    last_reason=reason,
                )
                self.request_stop(StopReason.FAULTS)
        if over_budget:
            metrics.add(semconv.METRIC_BUDGET_VIOLATIONS, 1, self._metric_attrs)
        telemetry = self._telemetry
        telemetry.record_ms(semconv.METRIC_TICK_DURATION, result.tick_ms, self._metric_attrs)
        telemetry.record_ms(semconv.METRIC_INFERENCE_DURATION, result.inference_ms, self._metric_attrs)
        if stats.trace_id is None and span.get_span_context().is_valid:
            stats.trace_id = trace_id_hex(span)
        self.recent_ticks.append(result)
        if span.is_recording():
            return tick_span_attributes(result, self._metric_attrs)
        return None

    # -- the loop ------------------------------------------------------------------------

    def run(self, max_ticks: int | None = None, *, duration_s: float | None = None) -> RunResult:
        """Tick on the absolute schedule until ``max_ticks``, ``duration_s``, a stop or termination.

        Raises:
            ROSRuntimeError: The runner is not active.
            ROSDeadlineMissed: Under the ``raise`` policy; ``run_result`` holds the partial run.
        """
        self._require_active()
        if max_ticks is not None and max_ticks < 0:
            raise ROSConfigError(f"must be >= 0, got {max_ticks}", field="max_ticks")
        self._reset_counters()
        collector = BetweenTicksCollector() if self.garbage_collection is GarbageCollection.BETWEEN_TICKS else None
        if collector is not None:
            collector.start()
        try:
            n, stop_reason = self._loop(max_ticks, duration_s, collector)
        finally:
            if collector is not None:
                collector.stop()
                self.metadata["gc"] = collector.report
        self._telemetry_recorder.worker.flush()
        return self._build_run_result(n, stop_reason)

    def _loop(
        self, max_ticks: int | None, duration_s: float | None, collector: BetweenTicksCollector | None
    ) -> tuple[int, StopReason]:
        """The schedule: one tick per slot; returns the ticks run and why the loop stopped."""
        clock = self._clock
        period = self.period_s
        t0 = self._schedule_origin()
        self._stats.run_t0 = t0
        end_limit = None if duration_s is None else t0 + duration_s
        slot = 0
        n = 0
        stop_reason = StopReason.MAX_TICKS
        while True:
            if self._stop_reason is not None:
                stop_reason = self._stop_reason
                if stop_reason in _PER_RUN_STOPS:
                    self._stop_reason = None  # answered by this run; the next run() starts afresh
                break
            if max_ticks is not None and n >= max_ticks:
                break
            slot_start = clock.now() if self.free_running else t0 + slot * period
            if end_limit is not None and slot_start >= end_limit:
                stop_reason = StopReason.DURATION
                break
            tick = self._next_tick(slot_start, math.inf if self.free_running else slot_start + period)
            try:
                self._run_tick(tick, slot_start_s=slot_start)
            except ROSDeadlineMissed as exc:
                n += 1
                self._stats.run_t_end = clock.now()
                self._count_start(tick.start_s, slot_start, first=n == 1)
                exc.run_result = self._build_run_result(n, StopReason.DEADLINE)
                self._telemetry_recorder.worker.flush()
                raise
            n += 1
            end = clock.now()
            self._count_start(tick.start_s, slot_start, first=n == 1)
            self._stats.run_t_end = end
            if self._should_terminate():
                stop_reason = StopReason.TERMINATED
                break
            if self.free_running:  # no idle time: collect whenever a generation is due
                if collector is not None:
                    collector.collect_if_due(math.inf)
                continue
            next_slot = slot + 1
            if end > t0 + next_slot * period:
                next_slot = int((end - t0) / period) + 1
                skipped = next_slot - slot - 1
                if skipped > 0:
                    self._stats.missed_slots += skipped
                    metrics.add(semconv.METRIC_MISSED_SLOTS, skipped, self._metric_attrs)
                    self._on_missed_slots(skipped)
                    if self._should_terminate():  # the world, stepped through the skipped slots, ended the run
                        stop_reason = StopReason.TERMINATED
                        break
            slot = next_slot
            if collector is not None:
                collector.collect_if_due(t0 + slot * period - clock.now())
        return n, stop_reason

    def _count_start(self, start: float, slot_start: float, *, first: bool) -> None:
        """Record when a tick started against its slot (after the tick, off its critical path)."""
        stats = self._stats
        if first:
            stats.first_start_s = start
        stats.last_start_s = start
        stats.jitter_us.add((start - slot_start) * 1e6)

    # -- results -------------------------------------------------------------------------

    def _reset_counters(self) -> None:
        self._stats.reset()
        self.recent_ticks.clear()

    def _build_run_result(self, n_ticks: int, stop_reason: StopReason) -> RunResult:
        return self._stats.result(
            runner_name=self.runner_name,
            skill_id=self.skill_id,
            rate_hz=self.rate_hz,
            n_ticks=n_ticks,
            stop_reason=stop_reason,
            metadata=dict(self.metadata),
        )

    def live_status(self) -> dict[str, float]:
        """A cheap snapshot for a status display, readable from another thread while running.

        See :meth:`openral_runner.stats.RunStats.live_status` for what each figure means.
        """
        stats = self._stats
        elapsed = self._clock.now() - stats.run_t0 if stats.run_t0 else 0.0
        return stats.live_status(list(self.recent_ticks), elapsed_s=elapsed, rate_hz=self.rate_hz)

    def _require_active(self) -> None:
        if not self._active:
            raise ROSRuntimeError(f"{self.runner_name} is not active: call activate() first")
