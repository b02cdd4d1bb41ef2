"""Deferred telemetry: phase spans and metric samples recorded as plain data, exported off the tick thread.

A recorded SDK span costs the tick thread about ten microseconds and a histogram record about
five. The tick thread instead records each phase as a :class:`DeferredSpan` (name, wall-clock
start and end, attributes, events, status) and each metric sample as a tuple into one
:class:`TickTelemetry` per tick; at the end of the tick the batch goes to a
:class:`TelemetryWorker`, which creates the real spans with their recorded times under the tick
span and records the samples. The live spans of a tick (the tick span itself, and those user code
runs under) are ended by the worker too, at the end time the tick thread recorded, after it has
set their final attributes: ending a span is where the SDK hands it to its processors. The
exported spans carry the same names, parents, times, attributes and events as spans started and
ended on the tick thread would.

Whether anything is deferred is a capability of the installed OpenTelemetry API objects, checked
once (:func:`meter_provider_records`): with the API's no-op providers, metric samples are
recorded directly (a no-op call) and phase spans are the tick's own non-recording span.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Final

import structlog
from opentelemetry import metrics, trace
from opentelemetry.metrics import Histogram
from opentelemetry.trace import Span, Status, StatusCode, Tracer
from opentelemetry.util.types import Attributes

_log = structlog.get_logger(__name__)

_time_ns: Final = time.time_ns
_QUEUE_TICKS: Final = 4096
_WAIT_S: Final = 50e-6
_MAX_WAITS: Final = 200  # about 10 ms: a tick that long must not stall export for good


def meter_provider_records() -> bool:
    """Whether the global meter provider is an SDK one (anything but the API's proxy or no-op provider)."""
    return not type(metrics.get_meter_provider()).__module__.startswith("opentelemetry.metrics")


class DeferredSpan:
    """A phase span recorded as data; the subset of the ``Span`` API that phase code uses.

    ``attributes`` passed in are shared, not copied, until the span sets its own.
    """

    __slots__ = ("_own", "_sink", "attributes", "end_ns", "events", "name", "start_ns", "status")

    def __init__(self, sink: list[DeferredSpan], name: str, attributes: Attributes = None) -> None:
        self._sink = sink
        self.name = name
        self.attributes: Attributes = attributes
        self._own = False
        self.events: list[tuple[str, Attributes, int, BaseException | None]] | None = None
        self.status: Status | None = None
        self.end_ns = 0
        self.start_ns = _time_ns()

    def is_recording(self) -> bool:
        """Always ``True``: a deferred span exists only inside a recorded tick."""
        return True

    def _mutable(self) -> dict[str, Any]:
        if not self._own:
            self.attributes = dict(self.attributes or {})
            self._own = True
        return self.attributes  # type: ignore[return-value]

    def set_attribute(self, key: str, value: Any) -> None:
        """Set one attribute."""
        self._mutable()[key] = value

    def set_attributes(self, attributes: dict[str, Any]) -> None:
        """Set several attributes."""
        self._mutable().update(attributes)

    def add_event(self, name: str, attributes: Attributes = None, timestamp: int | None = None) -> None:
        """Record an event, stamped now unless ``timestamp`` (ns since the epoch) is given."""
        if self.events is None:
            self.events = []
        self.events.append((name, attributes, _time_ns() if timestamp is None else timestamp, None))

    def record_exception(self, exception: BaseException, attributes: Attributes = None) -> None:
        """Record ``exception``; the worker replays it with ``Span.record_exception`` at this time."""
        if self.events is None:
            self.events = []
        self.events.append(("exception", attributes, _time_ns(), exception))

    def set_status(self, status: Status | StatusCode, description: str | None = None) -> None:
        """Set the span's status."""
        self.status = status if isinstance(status, Status) else Status(status, description)

    def end(self, end_time: int | None = None) -> None:
        """Stamp the end and hand the span to its tick's batch."""
        self.end_ns = _time_ns() if end_time is None else end_time
        self._sink.append(self)


class TickTelemetry:
    """One tick's deferred phase spans and metric samples.

    Args:
        span: The tick span; phases of a tick it does not record use it instead of a span of their own.
        defer_metrics: Queue metric samples for the worker rather than recording them now.
    """

    __slots__ = ("defer_metrics", "ends", "record_spans", "samples", "span", "spans")

    def __init__(self, span: Span, *, defer_metrics: bool) -> None:
        self.span = span
        self.record_spans = span.is_recording()
        self.defer_metrics = defer_metrics
        self.spans: list[DeferredSpan] = []
        self.ends: list[tuple[Span, int, Attributes]] = []
        self.samples: list[tuple[Callable[[float, Attributes], None], float, Attributes]] = []

    def start_span(self, name: str, attributes: Attributes = None) -> Any:
        """A deferred phase span under the tick span, or the tick's span when it is not recorded."""
        if self.record_spans:
            return DeferredSpan(self.spans, name, attributes)
        return self.span

    def end_later(self, span: Span, attributes: Attributes = None) -> None:
        """End a live span now as far as its times go; its ``attributes`` are set and it is ended by the worker.

        In a tick that is not recorded the span is ended at once (``attributes`` would not be kept).
        """
        if self.record_spans:
            self.ends.append((span, _time_ns(), attributes))
        else:
            span.end()

    def record(self, histogram: Histogram, value: float, attributes: Attributes = None) -> None:
        """Record a histogram sample (now, or on the worker when metrics are deferred)."""
        if self.defer_metrics:
            self.samples.append((histogram.record, value, attributes))
        else:
            histogram.record(value, attributes)

    def record_ms(self, histogram: Histogram, value_ms: float, attributes: Attributes = None) -> None:
        """Like :meth:`record`, dropping negative and non-finite durations."""
        if value_ms >= 0.0 and math.isfinite(value_ms):
            self.record(histogram, value_ms, attributes)

    @property
    def pending(self) -> bool:
        """Whether the worker has anything to do for this tick."""
        return bool(self.spans or self.samples or self.ends)


class TelemetryWorker:
    """A background thread that exports deferred ticks; the tick thread never waits on it.

    :meth:`submit` appends to a bounded queue; when the queue is full the oldest tick is
    dropped and counted in :attr:`dropped`. Python threads share one interpreter lock, so the
    worker gives it up after every span it exports, and while :attr:`busy` is set (the tick
    thread sets it for the duration of a tick) it waits rather than compete with the tick.

    Args:
        tracer: Creates the exported spans.
        max_ticks: Ticks the queue holds before dropping the oldest.
    """

    def __init__(self, tracer: Tracer, *, max_ticks: int = _QUEUE_TICKS) -> None:
        self._tracer = tracer
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
                    item.set()
                    continue
                try:
                    self._export(item)
                    self._yield()
                except Exception as exc:  # telemetry must never take the robot down
                    _log.warning("deferred telemetry export failed", error=str(exc))

    def _yield(self) -> None:
        """Let the tick thread have the interpreter lock: at once, and for as long as a tick runs."""
        time.sleep(0)
        waited = 0
        while self.busy and self._running and waited < _MAX_WAITS:
            time.sleep(_WAIT_S)
            waited += 1

    def _export(self, batch: TickTelemetry) -> None:
        if batch.spans:
            parent = trace.set_span_in_context(batch.span)
            start_span = self._tracer.start_span
            for record in batch.spans:
                span = start_span(record.name, context=parent, attributes=record.attributes, start_time=record.start_ns)
                if record.events:
                    for name, attributes, stamp, exception in record.events:
                        if exception is None:
                            span.add_event(name, attributes, stamp)
                        else:
                            span.record_exception(exception, attributes, stamp)
                if record.status is not None:
                    span.set_status(record.status)
                span.end(record.end_ns)
                self._yield()
        for live, end_ns, attributes in batch.ends:
            if attributes:
                live.set_attributes(attributes)
            live.end(end_ns)
        for record_sample, value, attributes in batch.samples:
            record_sample(value, attributes)
