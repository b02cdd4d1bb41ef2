"""``PerceptionEventPublisher``: detectors on a worker over the newest frame of each camera, events to the sinks.

The publisher is a frame consumer, not an observer: frames come from the ``perception`` observer
(:class:`~openral_perception.observer.PerceptionObserver`, the frames of each tick) or from a
GStreamer event leg; either way :meth:`~PerceptionEventPublisher.submit` only stores a reference.
The worker (a :class:`~openral_observability.latest_observer.LatestPerKeyWorker`, keyed by camera) runs each
:class:`~openral_perception.detectors.base.EventDetector` and publishes what they find to the sinks
(Zenoh, ROS 2), with a span per detection and counters in telemetry.

* **Rate limit first.** A token bucket per (sensor, kind), refilled at ``rate_hz`` with room for
  ``burst``, is asked *before* a detector runs: a frame that finds it empty is dropped and
  counted, and costs nothing.
* **Newest frame wins.** One slot per sensor: a frame arriving while the worker is busy replaces
  the one waiting (counted as ``superseded``), so a slow detector sees fresh frames, never a backlog.
* **One view per frame.** Every detector gets the same
  :class:`~openral_perception.frame.DetectorFrame`, so the grey image is made once per frame and
  colour order is the frame's own business.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from typing import Final, Protocol, runtime_checkable

import structlog

from openral_core import ROSConfigError, SensorFrame
from openral_core.perception import PerceptionEvent
from openral_observability import metrics, semconv, tracer
from openral_observability.latest_observer import LatestPerKeyWorker
from openral_perception.detectors.base import EventDetector
from openral_perception.frame import DetectorFrame

_log = structlog.get_logger(__name__)

TOPIC_PREFIX: Final[str] = "/openral/perception"
"""ROS 2 topics: ``/openral/perception/<kind>`` (Zenoh keys: ``openral/<robot>/perception/<kind>``)."""

SUPERSEDED: Final = "superseded"
"""The drop reason of a frame replaced by a newer one of its camera before the worker reached it."""


class EventSink(Protocol):
    """Where events go (Zenoh, ROS 2, a test's list)."""

    def publish(self, event: PerceptionEvent) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class OpenableEventSink(Protocol):
    """A sink that opens its link (a session that listens or connects) when the publisher starts, not when built."""

    def open(self) -> None: ...


class TokenBucket:
    """``capacity`` tokens, refilled at ``refill_per_s``; :meth:`take` spends one if there is one."""

    def __init__(self, capacity: float, refill_per_s: float, *, now: Callable[[], float] = time.monotonic) -> None:
        if capacity < 1 or refill_per_s <= 0:
            raise ROSConfigError("a token bucket needs capacity >= 1 and a positive refill rate", field="rate_hz")
        self.capacity = float(capacity)
        self.refill_per_s = float(refill_per_s)
        self._now = now
        self._tokens = float(capacity)
        self._stamp = now()

    def take(self) -> bool:
        now = self._now()
        self._tokens = min(self.capacity, self._tokens + (now - self._stamp) * self.refill_per_s)
        self._stamp = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


class PerceptionEventPublisher(LatestPerKeyWorker[str, SensorFrame]):
    """Runs detectors on a worker over the newest frame of each sensor and publishes their events.

    :meth:`start` opens the sinks that open a link, then starts the worker; :meth:`close` lets the
    worker finish the frames waiting, stops it and closes the sinks. Both can be called again
    (a runner activated twice starts it twice).

    Args:
        detectors: One per kind (kinds must differ).
        sinks: Where events go; each is closed by :meth:`close`.
        rate_hz: Detections per second per (sensor, kind) at most (the bucket's refill).
        burst: Detections allowed back to back after a quiet spell (the bucket's capacity).
        now: The bucket's clock (monotonic seconds).

    Raises:
        ROSConfigError: Repeated kinds, or a rate that is not positive.
    """

    def __init__(
        self,
        detectors: Sequence[EventDetector],
        sinks: Sequence[EventSink] = (),
        *,
        rate_hz: float = 5.0,
        burst: int = 1,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        kinds = [detector.kind for detector in detectors]
        if len(set(kinds)) != len(kinds):
            raise ROSConfigError(f"detector kinds repeat: {kinds}", field="detectors", hint="one detector per kind")
        if not rate_hz > 0:
            raise ROSConfigError(f"must be positive, got {rate_hz}", field="rate_hz")
        super().__init__(name="openral-perception")
        self.detectors = list(detectors)
        self.sinks = list(sinks)
        self.rate_hz = rate_hz
        self.burst = burst
        self._now = now
        self._buckets: dict[tuple[str, str], TokenBucket] = {}
        self.dropped: dict[tuple[str, str], int] = {}
        """(sensor, kind) or (sensor, ``superseded``) → frames not looked at."""
        self.published: dict[str, int] = {}
        self._submit_lock = threading.Lock()
        self._counts_lock = threading.Lock()
        self._started = False

    @property
    def is_started(self) -> bool:
        """Between :meth:`start` and :meth:`close`."""
        return self._started

    @property
    def dropped_counts(self) -> dict[tuple[str, str], int]:
        """A copy of :attr:`dropped`: frames not looked at, by (sensor, kind) or (sensor, ``superseded``)."""
        with self._counts_lock:
            return dict(self.dropped)

    @property
    def waiting(self) -> int:
        """Frames handed over that the worker has not taken yet."""
        return self.pending

    def start(self) -> None:
        """Open the sinks that open a link, then start the worker. Idempotent.

        Raises:
            ROSConfigError: A sink cannot open its link (an endpoint in use, say).
        """
        if self._started:
            return
        for sink in self.sinks:
            if isinstance(sink, OpenableEventSink):
                sink.open()
        super().start()
        self._started = True

    def close(self) -> None:
        """Handle the frames waiting, stop the worker and close the sinks. Idempotent."""
        super().close()
        self._started = False

    def stop(self) -> None:
        """:meth:`close` (the name the specification gives it)."""
        self.close()

    def submit(self, frame: SensorFrame) -> None:
        """Hand a frame over (O(1), never waits): it replaces its sensor's frame still waiting, if any."""
        with self._submit_lock:
            replaced = self.replaced
            self.offer(frame.sensor_id, frame)
            superseded = self.replaced != replaced
        if superseded:
            self._count_drop((frame.sensor_id, SUPERSEDED))

    def handle_item(self, key: str, item: SensorFrame) -> None:
        self.process(item)

    def handle_close(self) -> None:
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as exc:  # a sink's own failure must not hide the others' closing
                _log.warning("perception sink failed to close", sink=type(sink).__name__, error=str(exc))

    def process(self, frame: SensorFrame | DetectorFrame) -> list[PerceptionEvent]:
        """Run every detector whose bucket allows it on one frame, publish and return the events (worker side).

        Raises:
            ValueError: A frame without pixels a detector can look at (compressed, 16-bit, no inline data).
        """
        view = frame if isinstance(frame, DetectorFrame) else DetectorFrame(frame)
        events: list[PerceptionEvent] = []
        for detector in self.detectors:
            key = (view.sensor_id, detector.kind)
            bucket = self._buckets.get(key)
            if bucket is None:
                bucket = self._buckets[key] = TokenBucket(self.burst, self.rate_hz, now=self._now)
            if not bucket.take():  # limited before the detector runs: a dropped frame costs nothing
                self._count_drop(key)
                continue
            event = self._detect(detector, view)
            if event is not None:
                events.append(event)
                self._publish(event)
        return events

    def _detect(self, detector: EventDetector, frame: DetectorFrame) -> PerceptionEvent | None:
        attributes = {semconv.ATTR_PERCEPTION_KIND: detector.kind, semconv.ATTR_SENSOR_ID: frame.sensor_id}
        with tracer().start_as_current_span(semconv.SPAN_PERCEPTION_DETECT, attributes=attributes) as span:
            try:
                metadata = detector.detect(frame)
            except Exception as exc:  # a detector is third-party code: count, log, go on
                self.errors += 1
                span.record_exception(exc)
                _log.warning("detector failed", kind=detector.kind, sensor=frame.sensor_id, error=str(exc))
                return None
            if metadata is None:
                return None
            summary = detector.summarise(metadata)
            span.add_event(semconv.EVENT_PERCEPTION, {semconv.ATTR_PERCEPTION_SUMMARY: summary})
        return PerceptionEvent.model_validate(
            {
                "kind": detector.kind,
                "sensor_id": frame.sensor_id,
                "stamp_ns": frame.stamp_ns,
                "width": frame.width,
                "height": frame.height,
                "summary": summary,
                "metadata": metadata.model_dump(),
            }
        )

    def _publish(self, event: PerceptionEvent) -> None:
        self.published[event.kind] = self.published.get(event.kind, 0) + 1
        metrics.add(semconv.METRIC_PERCEPTION_EVENTS, 1, {semconv.ATTR_PERCEPTION_KIND: event.kind})
        for sink in self.sinks:
            try:
                sink.publish(event)
            except Exception as exc:  # one sink down must not silence the others
                self.errors += 1
                _log.warning("perception sink failed", sink=type(sink).__name__, error=str(exc))

    def _count_drop(self, key: tuple[str, str]) -> None:
        with self._counts_lock:  # the submitting thread and the worker both count
            self.dropped[key] = self.dropped.get(key, 0) + 1
        metrics.add(semconv.METRIC_PERCEPTION_DROPPED, 1, {semconv.ATTR_PERCEPTION_KIND: key[1]})
