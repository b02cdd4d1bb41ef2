"""The tick recorder: how a runner records each tick, decided from the installed OpenTelemetry providers."""

from __future__ import annotations

from typing import Any, Final

from opentelemetry import context, metrics, trace
from opentelemetry.trace import NonRecordingSpan, Span, SpanContext, TraceFlags
from opentelemetry.util.types import Attributes

from openral_observability import telemetry_worker
from openral_observability.deferred import DeferredSpan, QuietTickTelemetry, TickTelemetry
from openral_observability.semconv import SPAN_TICK, TRACER_NAME
from openral_observability.span_pipeline import SdkSpanPipeline
from openral_observability.telemetry_worker import InProcessSink, TelemetryWorker

_SAMPLED: Final = int(TraceFlags.SAMPLED)


def meter_provider_records() -> bool:
    """Whether the global meter provider is an SDK one (anything but the API's proxy or no-op provider)."""
    return not type(metrics.get_meter_provider()).__module__.startswith("opentelemetry.metrics")


def tracer_provider_records(provider: trace.TracerProvider) -> bool:
    """Whether ``provider`` can record spans (anything but the API's proxy or no-op provider)."""
    return not type(provider).__module__.startswith("opentelemetry.trace")


class TickRecorder:
    """How a runner records its ticks: deferred spans under an SDK tracer, the API's spans otherwise.

    What is installed is looked at in :meth:`activate`, once per activation (providers are set
    once per process, usually before a runner activates; the API's proxy tracer keeps working
    for a provider installed later, live; with nothing installed at activation the ticks record
    nothing until the next activation). :meth:`begin` then makes each tick's
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
        self._quiet: QuietTickTelemetry | None = None

    @property
    def defers_spans(self) -> bool:
        """Whether ticks are recorded as deferred spans (an SDK tracer was found at activation)."""
        return self._pipeline is not None

    @property
    def begins_ahead(self) -> bool:
        """Whether :meth:`begin` may run before the tick's slot (``restart`` then moves its start).

        True when ticks are deferred or not recorded at all; a live API span keeps the start it was given.
        """
        return self._quiet is not None or self._pipeline is not None

    def activate(self) -> None:
        """Look at the installed providers and start the worker."""
        self.defer_metrics = meter_provider_records()
        provider = self._provider or trace.get_tracer_provider()
        self._pipeline = SdkSpanPipeline.of(provider.get_tracer(TRACER_NAME))
        offload = telemetry_worker.offload_sink() if self._provider is None else None
        if offload is not None:
            self.defer_metrics = True
        self.worker.sink = offload or InProcessSink(self._pipeline)
        records = offload is not None or self.defer_metrics or tracer_provider_records(provider)
        self._quiet = None if records else QuietTickTelemetry()
        self.worker.start()

    def deactivate(self, timeout_s: float = 10.0) -> None:
        """Flush and stop the worker."""
        self.worker.stop(timeout_s)

    def begin(self) -> TickTelemetry:
        """Start a tick: its span (not yet current) and the batch its phases record into."""
        if self._quiet is not None:
            return self._quiet
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
