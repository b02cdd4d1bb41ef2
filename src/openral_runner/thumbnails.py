"""Per-camera thumbnails: small JPEGs at ``rate_hz``, encoded once, off the tick thread, for every viewer.

:class:`ThumbnailPublisher` is the ``thumbnails`` observer, on the newest-per-camera discipline.
On the tick thread it only takes a reference to
a camera's frame when that camera's next thumbnail is due (O(1), no pixels touched). A worker
thread downscales to at most 640×480 and encodes JPEG once (a JPEG frame that small passes
through as it is), then hands the thumbnail to every subscriber: a ``sensors.thumbnail`` span
carrying it (base64) for dashboards and exporters, and any observer that implements
:class:`ThumbnailSubscriber` (the Foxglove view). Each camera keeps an absolute schedule: after a
stall the next thumbnail is a full period later, never a burst. If encoding falls behind, a
camera's pending frame is replaced by its newer one rather than queued (counted in ``replaced``).
"""

from __future__ import annotations

import base64
import io
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import structlog
from PIL import Image
from pydantic import BaseModel, ConfigDict, Field

from openral_core import FrameEncoding, ObserverContext, SensorFrame, TickResult, WorldState
from openral_core.config import validate_model
from openral_core.environment import MAX_CAMERA_FPS
from openral_observability import semconv, tracer
from openral_observability.latest_observer import LatestPerKeyObserver
from openral_observability.observer import Thumbnail, ThumbnailSubscriber

__all__ = ["Thumbnail", "ThumbnailParams", "ThumbnailPublisher", "ThumbnailSubscriber", "encode_thumbnail"]

_log = structlog.get_logger(__name__)

MAX_WIDTH = 640
MAX_HEIGHT = 480


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
    elif frame.encoding is FrameEncoding.MONO8:
        image = Image.fromarray(np.ascontiguousarray(frame.as_array()))
    elif frame.channels >= 3:
        image = Image.fromarray(np.ascontiguousarray(frame.as_rgb()))
    else:
        return None
    image.thumbnail((MAX_WIDTH, MAX_HEIGHT), Image.Resampling.BILINEAR)
    out = io.BytesIO()
    image.save(out, format="JPEG", quality=quality)
    return Thumbnail(frame.sensor_id, frame.stamp_ns, image.width, image.height, out.getvalue(), frame.frame_id)


class ThumbnailParams(BaseModel):
    """Parameters of the ``thumbnails`` observer."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rate_hz: float = Field(default=10.0, ge=0, le=MAX_CAMERA_FPS)
    """Thumbnails per second per camera; 0 disables them."""
    quality: int = Field(default=70, ge=1, le=95)
    """JPEG quality."""


class ThumbnailPublisher(LatestPerKeyObserver[str, SensorFrame]):
    """Throttles, encodes and hands out thumbnails of every camera the skill sees (observer ``thumbnails``).

    The runner connects every observer that is a :class:`ThumbnailSubscriber` to it at activation.

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
        super().__init__(name="openral-thumbnails")
        self.rate_hz = rate_hz
        self.period_s = 1.0 / rate_hz if rate_hz > 0 else 0.0
        self.quality = quality
        self._sinks: list[Callable[[Thumbnail], None]] = [sink or _emit_span]
        self._clock = clock
        self._due: dict[str, float] = {}
        self._latest: dict[str, Thumbnail] = {}
        self.sink_errors = 0

    @classmethod
    def from_config(cls, params: Mapping[str, Any], context: ObserverContext) -> ThumbnailPublisher:
        """Plugin constructor (observer ``thumbnails``); ``params`` are validated as :class:`ThumbnailParams`.

        Raises:
            ROSConfigError: A wrong parameter (named with the allowed keys).
        """
        config = validate_model(ThumbnailParams, dict(params), field_prefix="observers[].params")
        return cls(config.rate_hz, quality=config.quality)

    @property
    def enabled(self) -> bool:
        """False when ``rate_hz`` is 0."""
        return self.rate_hz > 0

    @property
    def encoded(self) -> int:
        """Frames handed to the encoder."""
        return int(self.handled)

    def start(self) -> None:
        """Start the encoding thread (not when disabled). Idempotent."""
        if self.enabled:
            super().start()

    def stop(self) -> None:
        """Stop the encoding thread after what is pending (a later :meth:`start` restarts it)."""
        self.close()

    def subscribe(self, sink: Callable[[Thumbnail], None]) -> None:
        """Also hand every thumbnail to ``sink`` (on the worker thread). Subscribing twice has no effect."""
        if sink not in self._sinks:
            self._sinks.append(sink)

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Offer each frame the skill saw this tick (tick thread; O(1) per camera)."""
        frames = None if world is None else world.image_frames
        if frames:
            for frame in frames.values():
                self.offer_frame(frame)

    def offer_frame(self, frame: SensorFrame) -> bool:
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
        self.offer(frame.sensor_id, frame)
        return True

    def latest(self, sensor_id: str) -> Thumbnail | None:
        """The most recent thumbnail of one camera."""
        return self._latest.get(sensor_id)

    def handle_item(self, key: str, item: SensorFrame) -> None:
        """Encode one camera's newest due frame and hand the thumbnail to every sink (worker thread)."""
        thumb = encode_thumbnail(item, quality=self.quality)
        if thumb is None:
            return
        self._latest[key] = thumb
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
