"""The telemetry worker: a stalled export never blocks the tick thread, and drops are counted."""

from __future__ import annotations

import threading

from opentelemetry import trace

from openral_observability.deferred import DeferredSpan, MetricSample, TickTelemetry
from openral_observability.span_pipeline import SpanRecord
from openral_observability.telemetry_worker import TelemetryWorker


class StallingSink:
    """A span sink that blocks until released, like an exporter stuck on the network."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.started = threading.Event()
        self.finished = threading.Event()

    def export(self, spans: list[SpanRecord], samples: list[MetricSample]) -> None:
        self.started.set()
        self.release.wait(60)
        self.finished.set()

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
        batches = [_batch() for _ in range(1000)]
        submitter = threading.Thread(target=lambda: [worker.submit(batch) for batch in batches])
        submitter.start()
        submitter.join(30)  # about a microsecond each; a submit that waits for room waits for the release
        assert not submitter.is_alive(), "submit waited on the stalled worker"
        assert not sink.finished.is_set()  # every submit returned while the worker was still stuck
        assert worker.dropped == 1000 - 8
        assert not worker.flush(timeout_s=0.05)  # still stuck: flush gives up, it does not hang
    finally:
        sink.release.set()
        worker.stop()
    assert worker.flush()  # stopped and drained
