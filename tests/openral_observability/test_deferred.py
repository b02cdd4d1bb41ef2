"""Deferred telemetry: a stalled worker never blocks the tick thread, and drops are counted."""

from __future__ import annotations

import threading
import time
from typing import Any

from opentelemetry import trace

from openral_observability.deferred import DeferredSpan, TelemetryWorker, TickTelemetry


class StallingTracer:
    """A tracer whose ``start_span`` blocks until released, like an exporter stuck on the network."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.started = threading.Event()

    def start_span(self, *_args: Any, **_kwargs: Any) -> trace.Span:
        self.started.set()
        self.release.wait(10)
        return trace.INVALID_SPAN


def _batch() -> TickTelemetry:
    parent = trace.NonRecordingSpan(trace.SpanContext(1, 2, is_remote=False, trace_flags=trace.TraceFlags(1)))
    batch = TickTelemetry(parent, defer_metrics=False)
    batch.record_spans = True
    batch.start_span("phase").end()
    return batch


def test_a_stalled_worker_never_blocks_submit_and_counts_drops() -> None:
    tracer = StallingTracer()
    worker = TelemetryWorker(tracer, max_ticks=8)  # type: ignore[arg-type]
    worker.start()
    try:
        worker.submit(_batch())
        assert tracer.started.wait(5)  # the worker is now stuck on the first batch
        start = time.perf_counter()
        for _ in range(1000):
            worker.submit(_batch())
        elapsed_s = time.perf_counter() - start
        assert elapsed_s < 0.5  # about a microsecond each; nothing waited on the worker
        assert worker.dropped == 1000 - 8
        assert not worker.flush(timeout_s=0.05)  # still stuck: flush gives up, it does not hang
    finally:
        tracer.release.set()
        worker.stop()
    assert worker.flush()  # stopped and drained


def test_deferred_span_keeps_shared_attributes_unmodified() -> None:
    shared = {"k": "v"}
    sink: list[DeferredSpan] = []
    span = DeferredSpan(sink, "phase", shared)
    span.set_attribute("extra", 1)
    span.add_event("e", {"a": 1})
    span.end()
    assert shared == {"k": "v"}
    assert span.attributes == {"k": "v", "extra": 1}
    assert sink == [span]
    assert span.start_ns <= span.events[0][2] <= span.end_ns  # type: ignore[index]


def test_an_unrecorded_tick_uses_its_own_span_for_phases() -> None:
    tick = trace.NonRecordingSpan(trace.SpanContext(1, 2, is_remote=False))
    batch = TickTelemetry(tick, defer_metrics=False)
    assert batch.start_span("phase") is tick
    assert not batch.pending
