"""Perception events beside the policy: detectors that never hold the camera or the tick back.

A camera's event leg (the tee branch ``enable_event_tee`` adds, or the frames the runner already
has, through :class:`openral_runner.perception.PerceptionObserver`) hands frames to a
:class:`PerceptionEventPublisher`. Its worker runs each :class:`EventDetector` and publishes what
they find to the sinks (Zenoh, ROS 2), with a span per detection and counters in telemetry.

* **Rate limit first.** A token bucket per (sensor, kind), refilled at ``rate_hz`` with room for
  ``burst``, is asked *before* a detector runs: a frame that finds it empty is dropped and
  counted, and costs nothing.
* **Newest frame wins.** One slot per sensor: a frame arriving while the worker is busy replaces
  the one waiting (counted), so a slow detector sees fresh frames, never a backlog.
* **Detectors are plain numpy** over BGR (or grey) frames, taken as an appsink hands them over
  (a flat buffer, its size given by width and height) or as arrays (:func:`frame_pixels` views
  either without a copy): :class:`MotionDetector` (a per-pixel
  threshold, changes counted per cell so a noisy pixel neither fires nor widens the box) and
  :class:`SceneChangeDetector` (grey histograms compared by chi-square over the full 0–255
  range). No GStreamer needed.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Final, Protocol, TypeAlias, runtime_checkable

import numpy as np
import structlog
from pydantic import BaseModel

from openral_core import ROSConfigError
from openral_core.perception import MotionMetadata, PerceptionEvent, PixelBox, SceneChangeMetadata
from openral_observability import metrics, semconv, tracer

_log = structlog.get_logger(__name__)

TOPIC_PREFIX: Final[str] = "/openral/perception"
"""ROS 2 topics: ``/openral/perception/<kind>`` (Zenoh keys: ``openral/<robot>/perception/<kind>``)."""


FrameBuffer: TypeAlias = np.ndarray | bytes | bytearray | memoryview
"""A frame as detectors receive it: an appsink's flat BGR buffer, or an ``(H, W, 3)`` / ``(H, W)`` array."""


class EventDetector(Protocol):
    """Finds one kind of event in a frame."""

    kind: str

    def detect(self, frame_bgr: FrameBuffer, width: int, height: int, sensor_id: str) -> BaseModel | None:
        """What this frame shows (``None``: nothing worth an event).

        ``frame_bgr`` is ``width`` × ``height`` BGR: flat (an appsink's buffer) or shaped, or an
        ``(H, W)`` grey array; :func:`frame_pixels` turns any of them into an array view.
        """
        ...

    def summarise(self, metadata: Any) -> str:
        """One line for people."""
        ...


class EventSink(Protocol):
    """Where events go (Zenoh, ROS 2, a test's list)."""

    def publish(self, event: PerceptionEvent) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class OpenableEventSink(Protocol):
    """A sink that opens its link (a session that listens or connects) when the publisher starts, not when built."""

    def open(self) -> None: ...


def frame_pixels(frame: FrameBuffer, width: int, height: int) -> np.ndarray:
    """``frame`` as ``(height, width, 3)`` BGR (or ``(height, width)`` grey) ``uint8``, a view where possible.

    A flat buffer (bytes, a memoryview, a 1-D array) holds ``height`` rows of ``width * 3`` bytes,
    each padded to a multiple of 4 bytes or not (GStreamer pads BGR rows): it is viewed, not
    copied, padding cut off. A shaped array is taken as it is, once its size is checked.

    Raises:
        ValueError: A size that is not ``width`` × ``height``, or elements that are not bytes.
    """
    if width < 1 or height < 1:
        raise ValueError(f"a frame is at least 1x1 pixels, got {width}x{height}")
    array = frame if isinstance(frame, np.ndarray) else np.asarray(memoryview(frame))
    if array.dtype != np.uint8:
        raise ValueError(f"a frame holds uint8 pixels, got {array.dtype}")
    row = width * 3
    if array.ndim == 1:
        stride = -(-row // 4) * 4
        if array.size == row * height:
            return array.reshape(height, width, 3)
        if array.size == stride * height:
            return array.reshape(height, stride)[:, :row].reshape(height, width, 3)
        raise ValueError(
            f"a {width}x{height} BGR frame is {row * height} bytes ({stride * height} with padded rows), "
            f"got a buffer of {array.size}"
        )
    if array.shape[:2] == (height, width) and (array.ndim == 2 or (array.ndim == 3 and array.shape[2] >= 3)):
        return array
    raise ValueError(f"expected a {width}x{height} frame: (H, W, 3) BGR, (H, W) grey or flat, got shape {array.shape}")


def grey_levels(frame: np.ndarray) -> np.ndarray:
    """BT.601 luma of a BGR ``(H, W, 3)`` uint8 frame as ``uint8`` (a grey frame is returned as is).

    Integer weights summing to 256, computed in 32 bits: no level can wrap, whatever the input.
    """
    if frame.ndim == 2:
        return np.asarray(frame, dtype=np.uint8)
    if frame.ndim != 3 or frame.shape[2] < 3:
        raise ValueError(f"expected an (H, W, 3) BGR or (H, W) grey frame, got shape {frame.shape}")
    pixels = frame[..., :3].astype(np.uint32)
    weighted = pixels[..., 0] * 29 + pixels[..., 1] * 150 + pixels[..., 2] * 77 + 128
    return (weighted >> 8).astype(np.uint8)


class MotionDetector:
    """Motion since the previous frame, by cells.

    A pixel changed when its grey level moved by more than ``threshold``. A ``cell``×``cell``
    block changed when at least ``min_cell_fraction`` of its pixels did; an event needs
    ``min_cells`` changed cells, and its box spans the changed cells only. Sensor noise and
    single hot pixels therefore neither fire nor stretch the box.
    """

    kind = "motion"

    def __init__(
        self, *, threshold: float = 25.0, cell: int = 8, min_cell_fraction: float = 0.25, min_cells: int = 2
    ) -> None:
        if not 0 <= threshold < 255:
            raise ROSConfigError(f"threshold {threshold} is not a grey-level step in [0, 255)", field="threshold")
        if cell < 1 or not 0 < min_cell_fraction <= 1 or min_cells < 1:
            raise ROSConfigError("cell >= 1, 0 < min_cell_fraction <= 1 and min_cells >= 1 are required", field="cell")
        self.threshold = threshold
        self.cell = cell
        self.min_cell_fraction = min_cell_fraction
        self.min_cells = min_cells
        self._previous: dict[str, np.ndarray] = {}

    def detect(self, frame_bgr: FrameBuffer, width: int, height: int, sensor_id: str) -> MotionMetadata | None:
        """Motion against this sensor's previous frame (``None`` for its first, or after a size change)."""
        grey = grey_levels(frame_pixels(frame_bgr, width, height))
        previous = self._previous.get(sensor_id)
        self._previous[sensor_id] = grey
        if previous is None or previous.shape != grey.shape:
            return None
        changed = np.abs(grey.astype(np.int16) - previous.astype(np.int16)) > self.threshold
        cell = self.cell
        rows, cols = -(-grey.shape[0] // cell), -(-grey.shape[1] // cell)
        padded = np.zeros((rows * cell, cols * cell), dtype=np.uint16)
        padded[: grey.shape[0], : grey.shape[1]] = changed
        counts = padded.reshape(rows, cell, cols, cell).sum(axis=(1, 3))
        cells = counts >= self.min_cell_fraction * cell * cell
        n_cells = int(cells.sum())
        if n_cells < self.min_cells:
            return None
        cell_rows = np.flatnonzero(cells.any(axis=1))
        cell_cols = np.flatnonzero(cells.any(axis=0))
        h, w = grey.shape
        box = PixelBox(
            x0=float(cell_cols[0] * cell),
            y0=float(cell_rows[0] * cell),
            x1=float(min((cell_cols[-1] + 1) * cell, w)),
            y1=float(min((cell_rows[-1] + 1) * cell, h)),
        )
        return MotionMetadata(changed_fraction=n_cells / cells.size, box=box)

    def summarise(self, metadata: MotionMetadata) -> str:
        box = metadata.box
        return (
            f"motion over {metadata.changed_fraction:.0%} of the view, "
            f"in ({box.x0:.0f}, {box.y0:.0f})–({box.x1:.0f}, {box.y1:.0f})"
        )


class SceneChangeDetector:
    """An abrupt change of the scene: the grey histogram against the previous frame's.

    Histograms of ``bins`` bins over the full 0–255 range, normalised; the distance is the
    symmetric chi-square ``sum((p - q)^2 / (p + q))``, from 0 (same) to 2 (disjoint). Above
    ``threshold`` is an event. A uniform 200-grey frame turning 240 is a change of 2.
    """

    kind = "scene_change"

    def __init__(self, *, threshold: float = 0.5, bins: int = 32) -> None:
        if not 0 < threshold <= 2:
            raise ROSConfigError(f"threshold {threshold} is outside (0, 2]", field="threshold")
        if not 2 <= bins <= 256:
            raise ROSConfigError(f"bins {bins} is outside [2, 256]", field="bins")
        self.threshold = threshold
        self.bins = bins
        self._previous: dict[str, tuple[np.ndarray, float]] = {}

    def histogram(self, grey: np.ndarray) -> np.ndarray:
        """The normalised histogram of a grey frame."""
        index = (grey.astype(np.uint32) * self.bins) >> 8
        counts = np.bincount(index.ravel(), minlength=self.bins).astype(np.float64)
        return counts / max(1.0, float(counts.sum()))

    def detect(self, frame_bgr: FrameBuffer, width: int, height: int, sensor_id: str) -> SceneChangeMetadata | None:
        """A scene change against this sensor's previous frame (``None`` for its first)."""
        grey = grey_levels(frame_pixels(frame_bgr, width, height))
        current = (self.histogram(grey), float(grey.mean()))
        previous = self._previous.get(sensor_id)
        self._previous[sensor_id] = current
        if previous is None:
            return None
        p, q = previous[0], current[0]
        total = p + q
        present = total > 0
        distance = float(((p[present] - q[present]) ** 2 / total[present]).sum())
        if distance <= self.threshold:
            return None
        return SceneChangeMetadata(distance=distance, mean_grey_before=previous[1], mean_grey_after=current[1])

    def summarise(self, metadata: SceneChangeMetadata) -> str:
        return (
            f"scene changed (distance {metadata.distance:.2f}; mean grey "
            f"{metadata.mean_grey_before:.0f} -> {metadata.mean_grey_after:.0f})"
        )


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


class PerceptionEventPublisher:
    """Runs detectors on a worker over the newest frame of each sensor and publishes their events.

    Args:
        detectors: One per kind (kinds must differ).
        sinks: Where events go; each is closed by :meth:`stop`.
        rate_hz: Detections per second per (sensor, kind) at most (the bucket's refill).
        burst: Detections allowed back to back after a quiet spell (the bucket's capacity).
        now: The bucket's clock (monotonic seconds).
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
            raise ROSConfigError(f"detector kinds repeat: {kinds}", field="detectors")
        if not rate_hz > 0:
            raise ROSConfigError(f"must be positive, got {rate_hz}", field="rate_hz")
        self.detectors = list(detectors)
        self.sinks = list(sinks)
        self.rate_hz = rate_hz
        self.burst = burst
        self._now = now
        self._buckets: dict[tuple[str, str], TokenBucket] = {}
        self.dropped: dict[tuple[str, str], int] = {}
        """(sensor, reason) or (sensor, kind) → frames not looked at: ``superseded`` or rate-limited per kind."""
        self.published: dict[str, int] = {}
        self.errors = 0
        self._slots: dict[str, tuple[np.ndarray, int]] = {}
        self._wake = threading.Condition()
        self._closed = False
        self._thread: threading.Thread | None = None

    @property
    def is_started(self) -> bool:
        return self._thread is not None

    @property
    def dropped_counts(self) -> dict[tuple[str, str], int]:
        """A copy of :attr:`dropped`: frames not looked at, by (sensor, kind) or (sensor, ``superseded``)."""
        return dict(self.dropped)

    @property
    def waiting(self) -> int:
        """Frames handed over that the worker has not taken yet."""
        return len(self._slots)

    def start(self) -> None:
        """Open the sinks that open a link, then start the worker. Idempotent.

        Raises:
            ROSConfigError: A sink cannot open its link (an endpoint in use, say).
        """
        if self._thread is None:
            for sink in self.sinks:
                if isinstance(sink, OpenableEventSink):
                    sink.open()
            self._closed = False
            self._thread = threading.Thread(target=self._work, name="openral-perception", daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the worker and close the sinks. Idempotent."""
        with self._wake:
            self._closed = True
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        sinks, self.sinks = self.sinks, []
        for sink in sinks:
            try:
                sink.close()
            except Exception as exc:  # a sink's own failure must not hide the others' closing
                _log.warning("perception sink failed to close", error=str(exc))

    def submit(self, frame_bgr: np.ndarray, sensor_id: str, stamp_ns: int) -> None:
        """Hand a frame over (O(1), never waits): it replaces this sensor's frame still waiting, if any."""
        with self._wake:
            if sensor_id in self._slots:
                self._count_drop((sensor_id, "superseded"))
            self._slots[sensor_id] = (frame_bgr, stamp_ns)
            self._wake.notify()

    def process(self, frame_bgr: np.ndarray, sensor_id: str, stamp_ns: int) -> list[PerceptionEvent]:
        """Run every detector whose bucket allows it on one frame, publish and return the events (worker side)."""
        events: list[PerceptionEvent] = []
        for detector in self.detectors:
            key = (sensor_id, detector.kind)
            bucket = self._buckets.get(key)
            if bucket is None:
                bucket = self._buckets[key] = TokenBucket(self.burst, self.rate_hz, now=self._now)
            if not bucket.take():  # limited before the detector runs: a dropped frame costs nothing
                self._count_drop(key)
                continue
            event = self._detect(detector, frame_bgr, sensor_id, stamp_ns)
            if event is not None:
                events.append(event)
                self._publish(event)
        return events

    def _detect(
        self, detector: EventDetector, frame: np.ndarray, sensor_id: str, stamp_ns: int
    ) -> PerceptionEvent | None:
        height, width = frame.shape[:2]
        attributes = {semconv.ATTR_PERCEPTION_KIND: detector.kind, semconv.ATTR_SENSOR_ID: sensor_id}
        with tracer().start_as_current_span(semconv.SPAN_PERCEPTION_DETECT, attributes=attributes) as span:
            try:
                metadata = detector.detect(frame, width, height, sensor_id)
            except Exception as exc:  # a detector is third-party code: count, log, go on
                self.errors += 1
                span.record_exception(exc)
                _log.warning("detector failed", kind=detector.kind, sensor=sensor_id, error=str(exc))
                return None
            if metadata is None:
                return None
            summary = detector.summarise(metadata)
            span.add_event(semconv.EVENT_PERCEPTION, {semconv.ATTR_PERCEPTION_SUMMARY: summary})
        return PerceptionEvent.model_validate(
            {
                "kind": detector.kind,
                "sensor_id": sensor_id,
                "stamp_ns": stamp_ns,
                "width": width,
                "height": height,
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
        self.dropped[key] = self.dropped.get(key, 0) + 1
        metrics.add(semconv.METRIC_PERCEPTION_DROPPED, 1, {semconv.ATTR_PERCEPTION_KIND: key[1]})

    def _work(self) -> None:
        while True:
            with self._wake:
                while not self._slots and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                sensor_id = next(iter(self._slots))
                frame, stamp_ns = self._slots.pop(sensor_id)
            self.process(frame, sensor_id, stamp_ns)
