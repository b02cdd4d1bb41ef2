"""Per-camera thumbnails: small JPEGs at ``thumbnail_hz``, encoded once, off the tick thread, for every viewer.

:class:`ThumbnailPublisher` is a tick observer. On the tick thread it only takes a reference to
a camera's frame when that camera's next thumbnail is due (O(1), no pixels touched). A worker
thread downscales to at most 640×480 and encodes JPEG once (a JPEG frame that small passes
through as it is), then hands the thumbnail to every subscriber: a ``sensors.thumbnail`` span
carrying it (base64) for dashboards and exporters, and any observer that implements
:class:`ThumbnailSubscriber` (the Foxglove view). Each camera keeps an absolute schedule: after a
stall the next thumbnail is a full period later, never a burst. If encoding falls behind, older
pending frames are replaced by newer ones rather than queued.
"""

from __future__ import annotations

import base64
import io
import threading
import time
from collections.abc import Callable

import numpy as np
import structlog
from PIL import Image

from openral_core import FrameEncoding, SensorFrame, TickResult, WorldState
from openral_observability import semconv, tracer
from openral_observability.observer import Thumbnail, TickObserver

_log = structlog.get_logger(__name__)

MAX_WIDTH = 640
MAX_HEIGHT = 480

_TO_RGB: dict[FrameEncoding, Callable[[np.ndarray], np.ndarray]] = {
    FrameEncoding.RGB8: lambda a: a,
    FrameEncoding.BGR8: lambda a: a[:, :, ::-1],
    FrameEncoding.RGBA8: lambda a: a[:, :, :3],
    FrameEncoding.BGRA8: lambda a: a[:, :, 2::-1],
    FrameEncoding.MONO8: lambda a: a,
}


def encode_thumbnail(frame: SensorFrame, *, quality: int = 70) -> Thumbnail | None:
    """Downscale ``frame`` to fit 640×480 and JPEG-encode it; ``None`` for encodings it cannot show.

    A JPEG frame that already fits passes through untouched; larger JPEG and PNG frames are decoded first.
    """
    if frame.data is None:
        return None
    if frame.encoding in (FrameEncoding.JPEG, FrameEncoding.PNG):
        data = frame.data_bytes()
        if frame.encoding is FrameEncoding.JPEG and frame.width <= MAX_WIDTH and frame.height <= MAX_HEIGHT:
            return Thumbnail(frame.sensor_id, frame.stamp_ns, frame.width, frame.height, data, frame.frame_id)
        image = Image.open(io.BytesIO(data)).convert("RGB")
    else:
        convert = _TO_RGB.get(frame.encoding)
        if convert is None:
            return None
        image = Image.fromarray(np.ascontiguousarray(convert(frame.as_array())))
    image.thumbnail((MAX_WIDTH, MAX_HEIGHT), Image.Resampling.BILINEAR)
    out = io.BytesIO()
    image.save(out, format="JPEG", quality=quality)
    return Thumbnail(frame.sensor_id, frame.stamp_ns, image.width, image.height, out.getvalue(), frame.frame_id)


class ThumbnailPublisher(TickObserver):
    """Throttles, encodes and hands out thumbnails of every camera the skill sees.

    Args:
        rate_hz: Thumbnails per second per camera; 0 disables.
        quality: JPEG quality.
        sink: Called on the worker thread with each thumbnail (defaults to emitting a span).
        clock: Seconds clock for the schedule.
    """

    def __init__(
        self,
        rate_hz: float,
        *,
        quality: int = 70,
        sink: Callable[[Thumbnail], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.rate_hz = rate_hz
        self.period_s = 1.0 / rate_hz if rate_hz > 0 else 0.0
        self.quality = quality
        self._sinks: list[Callable[[Thumbnail], None]] = [sink or _emit_span]
        self._clock = clock
        self._due: dict[str, float] = {}
        self._pending: dict[str, SensorFrame] = {}
        self._latest: dict[str, Thumbnail] = {}
        self._cond = threading.Condition()
        self._stop = False
        self._thread: threading.Thread | None = None
        self.encoded = 0
        self.replaced = 0
        self.sink_errors = 0

    @property
    def enabled(self) -> bool:
        """False when ``rate_hz`` is 0."""
        return self.rate_hz > 0

    def start(self) -> None:
        """Start the encoding thread. Idempotent."""
        if not self.enabled or self._thread is not None:
            return
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="openral-thumbnails", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop and join the encoding thread. Idempotent."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def subscribe(self, sink: Callable[[Thumbnail], None]) -> None:
        """Also hand every thumbnail to ``sink`` (on the worker thread). Subscribing twice has no effect."""
        if sink not in self._sinks:
            self._sinks.append(sink)

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Offer each frame the skill saw this tick (tick thread; O(1) per camera)."""
        frames = None if world is None else world.image_frames
        if frames:
            for frame in frames.values():
                self.offer(frame)

    def close(self) -> None:
        """Stop the worker (a later :meth:`start` restarts it)."""
        self.stop()

    def offer(self, frame: SensorFrame) -> bool:
        """Hand over ``frame`` if its camera's next thumbnail is due (tick thread; O(1)).

        Returns:
            Whether the frame was taken.
        """
        if not self.enabled:
            return False
        now = self._clock()
        due = self._due.get(frame.sensor_id)
        if due is not None and now < due:
            return False
        # Keep phase while offers arrive on time; after a stall (more than half a period late)
        # restart the schedule from now, so the next thumbnail is a full period away: no burst.
        if due is None or now - due >= self.period_s / 2:
            self._due[frame.sensor_id] = now + self.period_s
        else:
            self._due[frame.sensor_id] = due + self.period_s
        with self._cond:
            if frame.sensor_id in self._pending:
                self.replaced += 1
            self._pending[frame.sensor_id] = frame
            self._cond.notify()
        return True

    def latest(self, sensor_id: str) -> Thumbnail | None:
        """The most recent thumbnail of one camera."""
        return self._latest.get(sensor_id)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                pending, self._pending = self._pending, {}
            for frame in pending.values():
                thumb = encode_thumbnail(frame, quality=self.quality)
                if thumb is None:
                    continue
                self._latest[frame.sensor_id] = thumb
                self.encoded += 1
                for sink in list(self._sinks):
                    try:
                        sink(thumb)
                    except Exception as exc:  # one viewer's failure must not starve the others
                        self.sink_errors += 1
                        if self.sink_errors == 1:
                            _log.error("thumbnail subscriber failed; counting further failures", error=repr(exc))


def _emit_span(thumb: Thumbnail) -> None:
    span = tracer().start_span(semconv.SPAN_SENSORS_THUMBNAIL)
    if span.is_recording():
        span.set_attributes(
            {
                semconv.ATTR_SENSOR_ID: thumb.sensor_id,
                semconv.ATTR_THUMBNAIL_WIDTH: thumb.width,
                semconv.ATTR_THUMBNAIL_HEIGHT: thumb.height,
                semconv.ATTR_THUMBNAIL_JPEG_B64: base64.b64encode(thumb.jpeg).decode("ascii"),
            }
        )
    span.end()
