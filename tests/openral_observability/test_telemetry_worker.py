"""The telemetry worker: a stalled export never blocks the tick thread, and drops are counted."""

from __future__ import annotations

import threading
import time

from opentelemetry import trace

from openral_observability.deferred import DeferredSpan, MetricSample, TickTelemetry
from openral_observability.span_pipeline import SpanRecord
from openral_observability.telemetry_worker import TelemetryWorker


class StallingSink:
    """A span sink that blocks until released, like an exporter stuck on the network."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.started = threading.Event()

    def export(self, spans: list[SpanRecord], samples: list[MetricSample]) -> None:
        self.started.set()
        self.release.wait(10)

    def flush(self, *, force: bool) -> None:
        pass


def _batch() -> TickTelemetry:
    sink: list[DeferredSpan] = []
    parent = trace.SpanContext(1, 2, is_remote=False, trace_flags=trace.TraceFlags(1))
    DeferredSpan(sink, "phase", parent, new_id=lambda: 3).end()
    return TickTelemetry(trace.INVALID_SPAN, defer_metrics=False, spans=sink)


def test_a_stalled_worker_never_blocks_submit_and_counts_drops() -> None:
    sink = StallingSink()
    worker = TelemetryWorker(sink, max_ticks=8)
    worker.start()
    try:
        worker.submit(_batch())
        assert sink.started.wait(5)  # the worker is now stuck on the first batch
        start = time.perf_counter()
        for _ in range(1000):
            worker.submit(_batch())
        elapsed_s = time.perf_counter() - start
        assert elapsed_s < 0.5  # about a microsecond each; nothing waited on the worker
        assert worker.dropped == 1000 - 8
        assert not worker.flush(timeout_s=0.05)  # still stuck: flush gives up, it does not hang
    finally:
        sink.release.set()
        worker.stop()
    assert worker.flush()  # stopped and drained
