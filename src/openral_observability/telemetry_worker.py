"""The telemetry worker: exports each tick's deferred spans and samples off the tick thread.

The tick thread hands a finished :class:`~openral_observability.deferred.TickTelemetry` to
:meth:`TelemetryWorker.submit` (a deque append); the worker thread turns its spans into
:class:`~openral_observability.span_pipeline.SpanRecord` values and passes them, with the metric
samples, to a :class:`TelemetrySink`: this process's SDK (:class:`InProcessSink`) or, under
``setup()``, the export process (:func:`offload_to`).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Final, Protocol

import structlog

from openral_observability.deferred import MetricSample, TickTelemetry
from openral_observability.metrics import histogram
from openral_observability.span_pipeline import SdkSpanPipeline, SpanRecord

_log = structlog.get_logger(__name__)

_QUEUE_TICKS: Final = 4096
_WAIT_S: Final = 50e-6
_MAX_WAITS: Final = 200  # about 10 ms: a tick that long must not stall export for good


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


def offload_sink() -> TelemetrySink | None:
    """The sink set by :func:`offload_to`, if any."""
    return _offload


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
