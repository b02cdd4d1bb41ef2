"""Deferred telemetry: a tick's spans and metric samples recorded as plain data, exported off the tick thread.

With an SDK tracer installed (see :mod:`openral_observability.span_pipeline`), the tick thread
makes no SDK span calls at all. Each span of a tick, the tick span included, is a
:class:`DeferredSpan`: a real ``opentelemetry.trace.Span`` that records its name, wall-clock
times, attributes, events and status into the tick's batch. The tick span's id is assigned up
front (``TickResult.trace_context`` and child spans need it). A phase span gets its id only
when something asks for it: the span user code runs under, as the parent of that code's own SDK
spans. Otherwise the worker assigns it. Metric samples are queued as
``(histogram name, value, attributes)`` tuples when the meter provider is an SDK one. At the end
of the tick the batch goes to the telemetry worker (:mod:`openral_observability.telemetry_worker`),
which hands the spans to the span processors and records the samples.

Which of this happens is decided by :class:`openral_observability.tick_recorder.TickRecorder`:
without an SDK tracer (the API's no-op provider, or another implementation), ticks use the API's
own spans, non-recording and nearly free under the no-op provider, live and exact under any other.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, Final

from opentelemetry.trace import INVALID_SPAN, Span, SpanContext, Status, StatusCode
from opentelemetry.util.types import Attributes

from openral_observability.metrics import histogram
from openral_observability.span_pipeline import SpanRecord, exception_attributes

_time_ns: Final = time.time_ns

MetricSample = tuple[str, float, Attributes]
"""``(histogram name, value, attributes)``: one sample of a millisecond histogram."""


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

    def end_into(self, sink: list[DeferredSpan] | None, end_time: int | None = None) -> None:
        """End the span into ``sink`` (a later tick's batch) instead of the one it started in; ``None`` drops it."""
        if sink is None:
            self.end_ns = self.end_ns or (_time_ns() if end_time is None else end_time)
            return
        self._sink = sink
        self.end(end_time)

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

    __slots__ = ("_start_span", "defer_metrics", "parents_spans", "samples", "span", "spans")

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
        self.parents_spans = span.get_span_context().is_valid
        """Whether spans user code starts during the tick should nest under it (nothing to parent otherwise)."""
        self._start_span = start_span
        self.spans: list[DeferredSpan] = [] if spans is None else spans
        self.samples: list[MetricSample] = []

    def start_span(self, name: str, attributes: Attributes = None) -> Span:
        """A child span of the tick, or the tick's own span when the tick is not recorded."""
        start = self._start_span
        return self.span if start is None else start(name, attributes)

    def start_lasting_span(self, name: str, attributes: Attributes = None) -> Span:
        """A child span of the tick that may end during a later tick (a chunk request, say).

        Its context is fixed now, so it can travel (as a ``traceparent``) before it ends. End it
        with :meth:`end_lasting_span` of the tick it ends in.
        """
        if self._start_span is None:
            return INVALID_SPAN
        span = self._start_span(name, attributes)
        if isinstance(span, DeferredSpan):
            span.get_span_context()
        return span

    def end_lasting_span(self, span: Span) -> None:
        """End a span made by :meth:`start_lasting_span` of an earlier tick; it is exported with this tick's batch.

        When this tick is not recorded, a deferred span is dropped (a sampled-out tick exports nothing).
        """
        if isinstance(span, DeferredSpan):
            span.end_into(self.spans if self._start_span is not None and isinstance(self.span, DeferredSpan) else None)
        else:
            span.end()

    def restart(self) -> None:
        """Move the tick span's start to now, for a tick prepared ahead of its slot."""
        span = self.span
        if isinstance(span, DeferredSpan):
            span.start_ns = _time_ns()

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


class QuietTickTelemetry(TickTelemetry):
    """The telemetry of a tick when nothing is installed to record it: every call returns at once.

    With the API's no-op tracer and meter providers the tick span is the invalid span and each
    metric sample would go to a no-op instrument; skipping the calls keeps the tick path short.
    """

    __slots__ = ()

    def __init__(self) -> None:
        super().__init__(INVALID_SPAN, defer_metrics=False)

    def record(self, name: str, value: float, attributes: Attributes = None) -> None:
        """Nothing records metrics: the sample is dropped."""

    def record_ms(self, name: str, value_ms: float, attributes: Attributes = None) -> None:
        """Nothing records metrics: the sample is dropped."""
