"""From an appsink's sample to a :class:`~openral_core.SensorFrame`: one copy, the real row stride, a capture stamp.

Every appsink the backend reads (the policy's leg, the event leg, a detector branch) goes through
:class:`SampleFrames`, so pixels are laid out in one place: the stride and offset come from the
caps' ``VideoInfo``, or from the buffer's video meta when the producer attached one (a camera's own
row layout), never from the buffer's length. Padded rows (161 BGR pixels = 483 bytes, padded to
484) come out as exactly ``width`` pixels, viewed over the one capture copy.

Capture stamps: a buffer's capture time is ``base_time + running_time(PTS)`` on the pipeline's
clock (the reader forces ``CLOCK_MONOTONIC``, the clock staleness is measured with). A buffer
without PTS is stamped on arrival; a stamp later than the arrival (a file decoded ahead of its
presentation time) is clamped to the arrival.

:class:`AppsinkTap` hands an extra appsink's frames (the event leg) to a callback.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import structlog

from openral_core import FrameEncoding, ROSRuntimeError, SensorFrame
from openral_runner.backends.gstreamer.gst import Gst, GstVideo
from openral_runner.backends.gstreamer.pipeline import PixelFormat
from openral_runner.frame_slot import frame_from_array

_log = structlog.get_logger(__name__)

ENCODINGS: dict[Any, FrameEncoding] = {
    GstVideo.VideoFormat.BGR: FrameEncoding.BGR8,
    GstVideo.VideoFormat.RGB: FrameEncoding.RGB8,
    GstVideo.VideoFormat.GRAY8: FrameEncoding.MONO8,
}
"""Raw formats that become frames, and the frame encoding of each."""

SUPPORTED_FORMATS: tuple[str, ...] = tuple(f.value for f in PixelFormat)
"""Raw formats the appsink accepts (``BGR`` → ``bgr8``, ``RGB`` → ``rgb8``, ``GRAY8`` → ``mono8``)."""

CONVERT_HINT = "end the pipeline with '! videoconvert ! video/x-raw,format=BGR ! appsink'"


@dataclass(frozen=True)
class SampleLayout:
    """How one negotiated caps lays pixels out in a buffer."""

    caps: Any
    encoding: FrameEncoding
    shape: tuple[int, ...]
    strides: tuple[int, ...]
    offset: int


class SampleFrames:
    """The samples of one appsink as frames of one sensor; the layout is worked out once per caps.

    Args:
        sensor_id: Names the frames (and the errors).
        width / height: The size the sensor declares; a sample of another size is an error.
            ``None``: any size.
        frame_id: Optical frame of the camera, copied into every frame.
    """

    def __init__(
        self, sensor_id: str, *, width: int | None = None, height: int | None = None, frame_id: str | None = None
    ) -> None:
        self.sensor_id = sensor_id
        self.width = width
        self.height = height
        self.frame_id = frame_id
        self._layout: SampleLayout | None = None
        self._seq = 0

    def reset(self) -> None:
        """Start counting frames from 0 again and forget the layout (a pipeline restarted)."""
        self._layout = None
        self._seq = 0

    def frame(self, sample: Any, sink: Any, arrival_ns: int) -> SensorFrame:
        """The frame of ``sample``: its pixels copied once out of the buffer, viewed with the real layout.

        Raises:
            ROSRuntimeError: Non-video caps, a format that is not a frame encoding, a size other
                than the declared one, or a buffer that cannot be mapped.
        """
        caps = sample.get_caps()
        layout = self._layout
        if layout is None or not caps.is_equal(layout.caps):
            layout = self._layout = self.layout_for(caps)
        buffer = sample.get_buffer()
        strides, offset = layout.strides, layout.offset
        meta = GstVideo.buffer_get_video_meta(buffer)
        if meta is not None:  # the producer's own plane layout wins over the caps' default one
            strides, offset = (int(meta.stride[0]), *layout.strides[1:]), int(meta.offset[0])
        ok, mapped = buffer.map(Gst.MapFlags.READ)
        if not ok:
            raise ROSRuntimeError(f"sensor '{self.sensor_id}': could not map a GStreamer buffer")
        try:
            data = mapped.data  # the capture copy: bytes owned by Python (the buffer goes back to its pool)
        finally:
            buffer.unmap(mapped)
        pixels = np.ndarray(layout.shape, np.uint8, buffer=data, offset=offset, strides=strides)
        seq = self._seq
        self._seq += 1
        return frame_from_array(
            self.sensor_id,
            pixels,
            stamp_ns=capture_stamp(sample, buffer, sink, arrival_ns),
            seq=seq,
            encoding=layout.encoding,
            frame_id=self.frame_id,
        )

    def layout_for(self, caps: Any) -> SampleLayout:
        """The layout ``caps`` give a buffer: shape, encoding, and the stride and offset of ``VideoInfo``.

        Raises:
            ROSRuntimeError: Non-video caps, an unsupported format, or a size other than the declared one.
        """
        info = GstVideo.VideoInfo.new_from_caps(caps)
        if info is None:
            raise ROSRuntimeError(f"sensor '{self.sensor_id}': the appsink got non-video caps {caps.to_string()}")
        encoding = ENCODINGS.get(info.finfo.format)
        if encoding is None:
            raise ROSRuntimeError(
                f"sensor '{self.sensor_id}': the pipeline delivers format {info.finfo.name}; the reader takes "
                f"{', '.join(SUPPORTED_FORMATS)} ({CONVERT_HINT})"
            )
        width, height = int(info.width), int(info.height)
        if (self.width is not None and width != self.width) or (self.height is not None and height != self.height):
            raise ROSRuntimeError(
                f"sensor '{self.sensor_id}': the pipeline delivers {width}x{height}, the sensor declares "
                f"{self.width}x{self.height}"
            )
        stride = int(info.stride[0])
        if encoding is FrameEncoding.MONO8:
            return SampleLayout(caps, encoding, (height, width), (stride, 1), int(info.offset[0]))
        return SampleLayout(caps, encoding, (height, width, 3), (stride, 3, 1), int(info.offset[0]))


def capture_stamp(sample: Any, buffer: Any, sink: Any, arrival_ns: int) -> int:
    """``base_time + running_time(PTS)`` on the pipeline clock, at most the arrival time."""
    pts = buffer.pts
    if pts == Gst.CLOCK_TIME_NONE:
        return arrival_ns
    running = sample.get_segment().to_running_time(Gst.Format.TIME, pts)
    if running == Gst.CLOCK_TIME_NONE:
        return arrival_ns
    return min(int(sink.get_base_time()) + int(running), arrival_ns)


class AppsinkTap:
    """Hands every sample of one appsink, as a frame, to ``on_frame`` (on the streaming thread).

    ``on_frame`` must not block: it holds the branch (a leaky queue ahead of it drops frames, the
    policy's leg never waits). A sample that cannot be read, or an ``on_frame`` that raises, is
    logged and counted in :attr:`errors`; the branch goes on.

    Args:
        sink: The appsink.
        frames: Turns its samples into frames.
        on_frame: Takes each frame.
    """

    def __init__(self, sink: Any, frames: SampleFrames, on_frame: Callable[[SensorFrame], None]) -> None:
        self.sink = sink
        self.frames = frames
        self.on_frame = on_frame
        self.errors = 0
        sink.set_property("emit-signals", True)
        self._handler: int | None = sink.connect("new-sample", self._on_sample)

    def detach(self) -> None:
        """Stop taking samples. Idempotent."""
        if self._handler is not None:
            self.sink.disconnect(self._handler)
            self._handler = None

    def _on_sample(self, sink: Any) -> Any:
        sample = sink.emit("pull-sample")  # the action signal: see ``gst`` on why not ``pull_sample()``
        if sample is None:  # flushing or EOS
            return Gst.FlowReturn.OK
        try:
            self.on_frame(self.frames.frame(sample, sink, time.monotonic_ns()))
        except Exception as exc:  # the streaming thread must survive a bad frame or a failing callback
            self.errors += 1
            _log.warning("appsink tap failed on a frame", sensor=self.frames.sensor_id, error=str(exc))
        return Gst.FlowReturn.OK
