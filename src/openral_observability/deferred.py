"""Deferred telemetry: a tick's spans and metric samples recorded as plain data, exported off the tick thread.

With an SDK tracer installed (see :mod:`openral_observability.span_pipeline`), the tick thread
makes no SDK span calls at all. Each span of a tick, the tick span included, is a
:class:`DeferredSpan`: a real ``opentelemetry.trace.Span`` that records its name, wall-clock
times, attributes, events and status into the tick's batch. The tick span's id is assigned up
front (``TickResult.trace_context`` and child spans need it). A phase span gets its id only
when something asks for it: the span user code runs under, as the parent of that code's own SDK
spans. Otherwise the worker assigns it. Metric samples are queued as
``(record, value, attributes)`` tuples when the meter provider is an SDK one. At the end of the
tick the batch goes to a :class:`TelemetryWorker`, which hands the spans to the span
processors and records the samples.

Without an SDK tracer (the API's no-op provider, or another implementation), ticks use the API's
own spans: non-recording and nearly free under the no-op provider, live and exact under any other.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Final, Protocol

import structlog
from opentelemetry import context, metrics, trace
from opentelemetry.trace import NonRecordingSpan, Span, SpanContext, Status, StatusCode, TraceFlags
from opentelemetry.util.types import Attributes

from openral_observability.metrics import histogram
from openral_observability.semconv import SPAN_TICK, TRACER_NAME
from openral_observability.span_pipeline import SdkSpanPipeline, SpanRecord, exception_attributes

_log = structlog.get_logger(__name__)

_time_ns: Final = time.time_ns
_QUEUE_TICKS: Final = 4096
_WAIT_S: Final = 50e-6
_MAX_WAITS: Final = 200  # about 10 ms: a tick that long must not stall export for good
_SAMPLED: Final = int(TraceFlags.SAMPLED)

MetricSample = tuple[str, float, Attributes]
"""``(histogram name, value, attributes)``: one sample of a millisecond histogram."""


def meter_provider_records() -> bool:
    """Whether the global meter provider is an SDK one (anything but the API's proxy or no-op provider)."""
    return not type(metrics.get_meter_provider()).__module__.startswith("opentelemetry.metrics")


class DeferredSpan(Span):
    """A span recorded as data on the tick thread and handed to the span processors by the worker.

    ``attributes`` passed in are shared, not copied, until the span sets its own.

    Args:
        sink: The tick's list of finished spans; :meth:`end` appends to it.
        name: Span name.
        parent: The parent's context (``None`` for a root span).
        attributes: Start attributes.
        span_context: This span's context, when it must be fixed now; otherwise it is made on first
            use from ``parent`` with an id from ``new_id``.
        new_id: Span id generator for the lazily made context.
    """

    # Class-level defaults: a phase span is created on the tick thread, so its constructor sets
    # only what every span has.
    _own = False
    events: list[tuple[str, Attributes, int, BaseException | None]] | None = None
    status: Status | None = None
    end_ns = 0

    def __init__(
        self,
        sink: list[DeferredSpan],
        name: str,
        parent: SpanContext | None,
        attributes: Attributes = None,
        *,
        span_context: SpanContext | None = None,
        new_id: Callable[[], int] | None = None,
    ) -> None:
        self._sink = sink
        self.name = name
        self.parent = parent
        self.attributes: Attributes = attributes
        self._context = span_context
        self._new_id = new_id
        self.start_ns = _time_ns()

    def get_span_context(self) -> SpanContext:
        """This span's context: a child of ``parent`` in its trace, with the parent's flags."""
        ctx = self._context
        if ctx is None:
            parent = self.parent
            if parent is None or self._new_id is None:
                raise RuntimeError(f"deferred span {self.name!r} has neither a context nor a parent to derive one from")
            ctx = SpanContext(
                parent.trace_id,
                self._new_id(),
                is_remote=False,
                trace_flags=parent.trace_flags,
                trace_state=parent.trace_state,
            )
            self._context = ctx
        return ctx

    def is_recording(self) -> bool:
        """``True`` until :meth:`end`."""
        return not self.end_ns

    def _mutable(self) -> dict[str, Any]:
        if not self._own:
            self.attributes = dict(self.attributes or {})
            self._own = True
        return self.attributes  # type: ignore[return-value]

    def set_attribute(self, key: str, value: Any) -> None:
        """Set one attribute (ignored once ended, as the SDK does)."""
        if not self.end_ns:
            self._mutable()[key] = value

    def set_attributes(self, attributes: Any) -> None:
        """Set several attributes (ignored once ended)."""
        if not self.end_ns:
            self._mutable().update(attributes)

    def adopt_attributes(self, attributes: dict[str, Any]) -> None:
        """Set ``attributes``, taking ownership of the dict (no copy when the span has none yet)."""
        if self.attributes is None and not self.end_ns:
            self.attributes = attributes
            self._own = True
        else:
            self.set_attributes(attributes)

    def add_event(self, name: str, attributes: Attributes = None, timestamp: int | None = None) -> None:
        """Record an event, stamped now unless ``timestamp`` (ns since the epoch) is given."""
        if self.events is None:
            self.events = []
        self.events.append((name, attributes, _time_ns() if timestamp is None else timestamp, None))

    def record_exception(
        self,
        exception: BaseException,
        attributes: Attributes = None,
        timestamp: int | None = None,
        escaped: bool = False,
    ) -> None:
        """Record ``exception``; the worker writes the SDK's ``exception.*`` attributes and formats the stack."""
        if self.events is None:
            self.events = []
        self.events.append(("exception", attributes, _time_ns() if timestamp is None else timestamp, exception))

    def set_status(self, status: Status | StatusCode, description: str | None = None) -> None:
        """Set the span's status."""
        self.status = status if isinstance(status, Status) else Status(status, description)

    def update_name(self, name: str) -> None:
        """Rename the span."""
        self.name = name

    def end(self, end_time: int | None = None) -> None:
        """Stamp the end and hand the span to its tick's batch. Only the first call counts."""
        if self.end_ns:
            return
        self.end_ns = _time_ns() if end_time is None else end_time
        self._sink.append(self)

    def to_record(self) -> SpanRecord:
        """This finished span as plain data; exceptions become the SDK's ``exception`` event attributes."""
        ctx = self.get_span_context()
        parent = self.parent
        events: list[tuple[str, Attributes, int]] = []
        for name, attributes, at, exception in self.events or ():
            events.append((name, attributes if exception is None else exception_attributes(exception, attributes), at))
        status = self.status
        return SpanRecord(
            self.name,
            ctx.trace_id,
            ctx.span_id,
            int(ctx.trace_flags),
            ctx.trace_state.to_header() if ctx.trace_state else None,
            None if parent is None else parent.span_id,
            False if parent is None else parent.is_remote,
            self.start_ns,
            self.end_ns,
            self.attributes,
            events,
            StatusCode.UNSET.value if status is None else status.status_code.value,
            None if status is None else status.description,
        )


class TickTelemetry:
    """One tick's span, its deferred spans and its metric samples.

    Args:
        span: The tick span.
        defer_metrics: Queue metric samples for the worker rather than recording them now.
        start_span: Makes a child span of the tick (deferred or live); ``None`` when the tick is
            not recorded, and its phases use the tick's own non-recording span.
        spans: The list deferred spans append themselves to when they end.
    """

    __slots__ = ("_start_span", "defer_metrics", "samples", "span", "spans")

    def __init__(
        self,
        span: Span,
        *,
        defer_metrics: bool,
        start_span: Callable[[str, Attributes], Span] | None = None,
        spans: list[DeferredSpan] | None = None,
    ) -> None:
        self.span = span
        self.defer_metrics = defer_metrics
        self._start_span = start_span
        self.spans: list[DeferredSpan] = [] if spans is None else spans
        self.samples: list[MetricSample] = []

    @property
    def record_spans(self) -> bool:
        """Whether this tick's phases get spans of their own."""
        return self._start_span is not None

    def start_span(self, name: str, attributes: Attributes = None) -> Span:
        """A child span of the tick, or the tick's own span when the tick is not recorded."""
        start = self._start_span
        return self.span if start is None else start(name, attributes)

    def finish(self, attributes: dict[str, Any] | None = None) -> None:
        """End the tick span with its final ``attributes`` (a dict the span may keep)."""
        span = self.span
        if attributes:
            if isinstance(span, DeferredSpan):
                span.adopt_attributes(attributes)
            elif span.is_recording():
                span.set_attributes(attributes)
        span.end()

    def record(self, name: str, value: float, attributes: Attributes = None) -> None:
        """Record a sample of the millisecond histogram ``name`` (now, or on the worker when metrics are deferred)."""
        if self.defer_metrics:
            self.samples.append((name, value, attributes))
        else:
            histogram(name).record(value, attributes)

    def record_ms(self, name: str, value_ms: float, attributes: Attributes = None) -> None:
        """Like :meth:`record`, dropping negative and non-finite durations."""
        if value_ms >= 0.0 and math.isfinite(value_ms):
            self.record(name, value_ms, attributes)

    @property
    def pending(self) -> bool:
        """Whether the worker has anything to do for this tick."""
        return bool(self.spans or self.samples)


class TelemetrySink(Protocol):
    """Where the worker hands each tick's finished spans and metric samples."""

    def export(self, spans: list[SpanRecord], samples: list[MetricSample]) -> None:
        """Export one tick's spans and samples (or buffer them until :meth:`flush`)."""
        ...

    def flush(self, *, force: bool) -> None:
        """Called whenever the worker has emptied its queue: send what is buffered (all of it when ``force``)."""
        ...


class InProcessSink:
    """Spans to this process's SDK span processors, samples to this process's histograms.

    Args:
        pipeline: The SDK tracer's pipeline; ``None`` when no span is deferred.
    """

    def __init__(self, pipeline: SdkSpanPipeline | None) -> None:
        self._pipeline = pipeline

    def export(self, spans: list[SpanRecord], samples: list[MetricSample]) -> None:
        """Hand the spans to the span processors and record the samples."""
        pipeline = self._pipeline
        if pipeline is not None:
            for span in spans:
                pipeline.end(span)
        for name, value, attributes in samples:
            histogram(name).record(value, attributes)

    def flush(self, *, force: bool) -> None:
        """Nothing is buffered here."""


_offload: TelemetrySink | None = None


def offload_to(sink: TelemetrySink | None) -> None:
    """Send deferred spans and samples of runners activated from now on to ``sink`` (``None``: this process).

    ``setup()`` points this at its export process, so encoding and posting OTLP never compete
    with the tick thread for the interpreter lock.
    """
    global _offload  # noqa: PLW0603  (one export destination per process, like the OTel globals)
    _offload = sink


class TelemetryWorker:
    """A background thread that exports deferred ticks; the tick thread never waits on it.

    :meth:`submit` appends to a bounded queue; when the queue is full the oldest tick is
    dropped and counted in :attr:`dropped`. Python threads share one interpreter lock, so the
    worker gives it up after every tick it exports, and while :attr:`busy` is set (the tick
    thread sets it for the duration of a tick) it waits rather than compete with the tick.

    Args:
        sink: Receives each tick's spans and samples; settable later (:attr:`sink`).
        max_ticks: Ticks the queue holds before dropping the oldest.
    """

    def __init__(self, sink: TelemetrySink | None = None, *, max_ticks: int = _QUEUE_TICKS) -> None:
        self.sink = sink
        self._max = max_ticks
        self._queue: deque[TickTelemetry | threading.Event] = deque()
        self._wake = threading.Event()
        self._running = False
        self._thread: threading.Thread | None = None
        self.dropped = 0
        self.busy = False

    def start(self) -> None:
        """Start the thread; a no-op when it runs."""
        if self._thread is not None:
            return
        self._running = True
        self._thread = threading.Thread(target=self._loop, name="openral-telemetry", daemon=True)
        self._thread.start()

    def submit(self, batch: TickTelemetry) -> None:
        """Queue one tick's batch without blocking; drops (and counts) the oldest when full."""
        queue = self._queue
        if len(queue) >= self._max:
            try:
                queue.popleft()
                self.dropped += 1
            except IndexError:
                pass
        queue.append(batch)
        if not self._wake.is_set():
            self._wake.set()

    def flush(self, timeout_s: float = 10.0) -> bool:
        """Wait until every batch submitted so far is exported; ``False`` on timeout or when not running."""
        if self._thread is None:
            return not self._queue
        done = threading.Event()
        self._queue.append(done)
        self._wake.set()
        return done.wait(timeout_s)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Flush, then end the thread. Idempotent."""
        thread = self._thread
        if thread is None:
            return
        self.flush(timeout_s)
        self._running = False
        self._wake.set()
        thread.join(timeout_s)
        self._thread = None

    def _loop(self) -> None:
        queue = self._queue
        while self._running or queue:
            self._wake.wait()  # an idle worker never wakes, so it never asks for the interpreter lock
            self._wake.clear()
            while queue:
                item = queue.popleft()
                if isinstance(item, threading.Event):
                    self._flush_sink(force=True)
                    item.set()
                    continue
                try:
                    self._export(item)
                except Exception as exc:  # telemetry must never take the robot down
                    _log.warning("deferred telemetry export failed", error=str(exc))
                if queue:
                    self._yield()
            self._flush_sink(force=False)

    def _flush_sink(self, *, force: bool) -> None:
        sink = self.sink
        if sink is not None:
            try:
                sink.flush(force=force)
            except Exception as exc:
                _log.warning("deferred telemetry flush failed", error=str(exc))

    def _yield(self) -> None:
        """Let the tick thread have the interpreter lock: at once, and for as long as a tick runs."""
        time.sleep(0)
        waited = 0
        while self.busy and self._running and waited < _MAX_WAITS:
            time.sleep(_WAIT_S)
            waited += 1

    def _export(self, batch: TickTelemetry) -> None:
        sink = self.sink
        if sink is not None:
            sink.export([span.to_record() for span in batch.spans], batch.samples)


class TickRecorder:
    """How a runner records its ticks: deferred spans under an SDK tracer, the API's spans otherwise.

    What is installed is looked at in :meth:`activate`, once per activation (providers are set
    once per process, usually before a runner activates; the API's proxy tracer keeps working
    for a provider installed later, live). :meth:`begin` then makes each tick's
    :class:`TickTelemetry`, and :meth:`end` hands it to the worker.

    Args:
        provider: The tracer provider to record with; the global one when ``None``.
    """

    def __init__(self, provider: trace.TracerProvider | None = None) -> None:
        self._provider = provider
        # Without an explicit provider, the API's proxy tracer: it follows a provider installed later.
        self._proxy = trace.get_tracer(TRACER_NAME, tracer_provider=provider)
        self._pipeline: SdkSpanPipeline | None = None
        self.defer_metrics = False
        self.worker = TelemetryWorker()
        self._direct = TickTelemetry(trace.INVALID_SPAN, defer_metrics=False)

    @property
    def defers_spans(self) -> bool:
        """Whether ticks are recorded as deferred spans (an SDK tracer was found at activation)."""
        return self._pipeline is not None

    def activate(self) -> None:
        """Look at the installed providers and start the worker."""
        self.defer_metrics = meter_provider_records()
        provider = self._provider or trace.get_tracer_provider()
        self._pipeline = SdkSpanPipeline.of(provider.get_tracer(TRACER_NAME))
        offload = _offload if self._provider is None else None
        if offload is not None:
            self.defer_metrics = True
        self.worker.sink = offload or InProcessSink(self._pipeline)
        self.worker.start()

    def deactivate(self, timeout_s: float = 10.0) -> None:
        """Flush and stop the worker."""
        self.worker.stop(timeout_s)

    def begin(self) -> TickTelemetry:
        """Start a tick: its span (not yet current) and the batch its phases record into."""
        pipeline = self._pipeline
        if pipeline is None:
            return self._begin_with_api()
        parent_context = context.get_current()
        parent: SpanContext | None = trace.get_current_span(parent_context).get_span_context()
        if parent is not None and parent.is_valid:
            trace_id = parent.trace_id
            random_flag = int(parent.trace_flags) & ~_SAMPLED
        else:
            parent = None
            trace_id = pipeline.new_trace_id()
            random_flag = pipeline.random_trace_id_flag
        decision = pipeline.sampler.should_sample(parent_context, trace_id, SPAN_TICK)
        flags = random_flag | _SAMPLED if decision.decision.is_sampled() else random_flag
        span_context = SpanContext(
            trace_id,
            pipeline.new_span_id(),
            is_remote=False,
            trace_flags=TraceFlags(flags),
            trace_state=decision.trace_state,
        )
        if not decision.decision.is_recording():
            return self._unrecorded(NonRecordingSpan(span_context))
        sink: list[DeferredSpan] = []
        new_id = pipeline.new_span_id
        tick = DeferredSpan(sink, SPAN_TICK, parent, decision.attributes or None, span_context=span_context)

        def start_span(name: str, attributes: Attributes) -> Span:
            return DeferredSpan(sink, name, span_context, attributes, new_id=new_id)

        return TickTelemetry(tick, defer_metrics=self.defer_metrics, start_span=start_span, spans=sink)

    def _begin_with_api(self) -> TickTelemetry:
        span = self._proxy.start_span(SPAN_TICK)
        if span.is_recording():  # a provider other than the SDK's: its spans are used live
            tick_context = trace.set_span_in_context(span)
            proxy = self._proxy

            def start_span(name: str, attributes: Attributes) -> Span:
                return proxy.start_span(name, context=tick_context, attributes=attributes)

            return TickTelemetry(span, defer_metrics=self.defer_metrics, start_span=start_span)
        return self._unrecorded(span)

    def _unrecorded(self, span: Span) -> TickTelemetry:
        if self.defer_metrics:
            return TickTelemetry(span, defer_metrics=True)
        direct = self._direct  # nothing to queue: one object serves every tick
        direct.span = span
        return direct

    def end(self, batch: TickTelemetry, attributes: dict[str, Any] | None = None) -> None:
        """End the tick span with ``attributes`` (a dict the span may keep) and queue what the worker must export."""
        batch.finish(attributes)
        if batch.pending:
            self.worker.submit(batch)

    def start_live_span(self, name: str, attributes: Attributes = None) -> Span:
        """A span started now through the API (for rare events such as an e-stop)."""
        return self._proxy.start_span(name, attributes=attributes)
