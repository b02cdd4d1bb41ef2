"""Detectors called the way an appsink hands a frame over: a BGR buffer, its width and height, the camera.

This is the detector form the specification fixes (``detect(frame_bgr, width, height, sensor_id)``,
``summarise(metadata)``), importable at ``openral_runner.backends.gstreamer.perception_tee``. A
buffer becomes a :class:`~openral_perception.frame.DetectorFrame` without a copy
(:func:`buffer_frame`), so the grey image and the histograms are those of the frame seam. Each
detector here also takes a ``DetectorFrame`` alone, so it runs in the event publisher like the
registered kinds; the object detector (:mod:`~openral_perception.detectors.objects`) takes both
forms through :func:`call_frame`.
"""

from __future__ import annotations

from typing import Any, Generic, Protocol, TypeAlias, TypeVar, overload

import numpy as np
from pydantic import BaseModel

from openral_core import FrameEncoding, ROSConfigError, SensorFrame
from openral_core.perception import MotionMetadata, PixelBox, SceneChangeMetadata
from openral_perception.detectors.motion import describe_motion
from openral_perception.detectors.scene_change import SceneChangeDetector, SceneChangeParams
from openral_perception.frame import DetectorFrame

FrameBuffer: TypeAlias = bytes | bytearray | memoryview | np.ndarray
"""A frame as an appsink hands it over (flat BGR), or an ``(H, W, 3)`` BGR / ``(H, W)`` grey uint8 array."""


class BufferEventDetector(Protocol):
    """Finds one kind of event in a frame given as a buffer and its size (the specification's detector)."""

    kind: str

    def detect(self, frame_bgr: FrameBuffer, width: int, height: int, sensor_id: str) -> BaseModel | None:
        """What this frame of ``sensor_id`` shows (``None``: nothing worth an event)."""
        ...

    def summarise(self, metadata: Any) -> str:
        """One line for people about what :meth:`detect` found."""
        ...


def buffer_frame(frame_bgr: FrameBuffer, width: int, height: int, sensor_id: str) -> DetectorFrame:
    """``frame_bgr`` as a detector's view of a ``width`` × ``height`` frame of ``sensor_id``, not copied.

    A flat buffer (bytes, a memoryview, a 1-D array) holds ``height`` rows of ``width * 3`` BGR
    bytes, tightly packed or each padded to a multiple of 4 bytes (GStreamer's BGR rows). A
    shaped array is ``(height, width, 3)`` BGR or ``(height, width)`` grey.

    Raises:
        ValueError: A size other than ``width`` × ``height``, or elements that are not bytes.
    """
    if width < 1 or height < 1:
        raise ValueError(f"a frame is at least 1x1 pixels, got {width}x{height}")
    pixels = frame_bgr if isinstance(frame_bgr, np.ndarray) else np.asarray(memoryview(frame_bgr))
    if pixels.dtype != np.uint8:
        raise ValueError(f"a frame holds uint8 pixels, got {pixels.dtype}")
    if pixels.ndim == 1:
        row = width * 3
        padded = -(-row // 4) * 4
        if pixels.size not in (row * height, padded * height):
            raise ValueError(
                f"a {width}x{height} BGR frame is {row * height} bytes ({padded * height} with padded rows), "
                f"got {pixels.size}"
            )
        stride = None if pixels.size == row * height else padded
        return DetectorFrame(
            SensorFrame(
                sensor_id=sensor_id,
                stamp_ns=0,
                width=width,
                height=height,
                encoding=FrameEncoding.BGR8,
                row_stride=stride,
                data=pixels,
            )
        )
    if pixels.shape[:2] == (height, width) and (pixels.ndim == 2 or (pixels.ndim == 3 and pixels.shape[2] == 3)):
        return DetectorFrame.from_array(pixels, sensor_id=sensor_id)
    raise ValueError(
        f"expected a {width}x{height} frame: flat BGR, (H, W, 3) BGR or (H, W) grey, got shape {pixels.shape}"
    )


def call_frame(
    frame_bgr: FrameBuffer | DetectorFrame, width: int | None, height: int | None, sensor_id: str | None
) -> DetectorFrame:
    """The frame a ``detect`` call names: a view given as is, or a buffer with its size and camera.

    Raises:
        TypeError: A view with a size or camera beside it, or a buffer without them.
        ValueError: A buffer whose size is not ``width`` × ``height`` (see :func:`buffer_frame`).
    """
    if isinstance(frame_bgr, DetectorFrame):
        if width is not None or height is not None or sensor_id is not None:
            raise TypeError("detect(frame) takes a DetectorFrame alone; width, height and sensor_id are its own")
        return frame_bgr
    if width is None or height is None or sensor_id is None:
        raise TypeError("detect(frame_bgr, width, height, sensor_id) needs the buffer's width, height and sensor_id")
    return buffer_frame(frame_bgr, width, height, sensor_id)


MetadataT = TypeVar("MetadataT", bound=BaseModel)


class BufferDetector(Generic[MetadataT]):
    """A detector called with a ``DetectorFrame`` alone, or with a BGR buffer, its size and its camera.

    Subclasses implement :meth:`detect_frame`; the two call forms meet in :func:`call_frame`.
    """

    @overload
    def detect(self, frame_bgr: DetectorFrame) -> MetadataT | None: ...

    @overload
    def detect(self, frame_bgr: FrameBuffer, width: int, height: int, sensor_id: str) -> MetadataT | None: ...

    def detect(
        self,
        frame_bgr: FrameBuffer | DetectorFrame,
        width: int | None = None,
        height: int | None = None,
        sensor_id: str | None = None,
    ) -> MetadataT | None:
        """The event in the frame, or ``None``.

        Raises:
            ValueError: A buffer whose size is not ``width`` × ``height`` (see :func:`buffer_frame`).
        """
        return self.detect_frame(call_frame(frame_bgr, width, height, sensor_id))

    def detect_frame(self, frame: DetectorFrame) -> MetadataT | None:
        """The event in ``frame``, or ``None``."""
        raise NotImplementedError


class BufferMotionDetector(BufferDetector[MotionMetadata]):
    """Motion as the mean change of grey level since the same camera's previous frame.

    Grey is BT.601 luma, taken every ``downsample`` pixels along both axes. The mean absolute
    change over those pixels, over 255 (0: the same frame; 1: black turned white everywhere), is
    an event when above ``threshold``: the default 0.02 is about 5 grey levels on average, which a
    hand moving fires and lighting drift does not. The event's box spans the pixels that changed
    at all, in the frame's own coordinates; ``changed_fraction`` is their share of the pixels
    compared. A camera's first frame, and its first after a size change, are only remembered.

    Raises:
        ROSConfigError: ``threshold`` outside [0, 1] or ``downsample`` not an integer >= 1.
    """

    kind = "motion"

    def __init__(self, *, threshold: float = 0.02, downsample: int = 1) -> None:
        if not 0 <= threshold <= 1:
            raise ROSConfigError(f"{threshold} is not a mean grey change in [0, 1]", field="threshold")
        if not isinstance(downsample, int) or isinstance(downsample, bool) or downsample < 1:
            raise ROSConfigError(f"{downsample!r} is not a pixel step >= 1", field="downsample")
        self.threshold = threshold
        self.downsample = downsample
        self._previous: dict[str, np.ndarray] = {}

    def detect_frame(self, frame: DetectorFrame) -> MotionMetadata | None:
        """Motion against this camera's previous frame (``None`` below the threshold, or nothing to compare with)."""
        step = self.downsample
        grey = self._grey(frame).astype(np.int16)  # a copy: the capture buffer may be reused
        previous = self._previous.get(frame.sensor_id)
        self._previous[frame.sensor_id] = grey
        if previous is None or previous.shape != grey.shape:
            return None
        delta = np.abs(grey - previous)
        if float(delta.mean()) / 255.0 <= self.threshold:
            return None
        changed = delta > 0
        rows = np.flatnonzero(changed.any(axis=1))
        cols = np.flatnonzero(changed.any(axis=0))
        box = PixelBox(
            x0=float(cols[0] * step),
            y0=float(rows[0] * step),
            x1=float(min((cols[-1] + 1) * step, frame.width)),
            y1=float(min((rows[-1] + 1) * step, frame.height)),
        )
        return MotionMetadata(changed_fraction=float(changed.mean()), box=box)

    def summarise(self, metadata: MotionMetadata) -> str:
        return describe_motion(metadata)

    def _grey(self, frame: DetectorFrame) -> np.ndarray:
        """The grey image compared: the frame's own, or of every ``downsample``-th pixel (fewer to turn grey)."""
        if self.downsample == 1:
            return frame.grey
        pixels = frame.frame.as_array()[:: self.downsample, :: self.downsample]
        return DetectorFrame.from_array(pixels, sensor_id=frame.sensor_id, encoding=frame.frame.encoding).grey


class BufferSceneChangeDetector(BufferDetector[SceneChangeMetadata]):
    """A scene change: 32-bin grey histograms of consecutive frames apart by more than ``threshold``.

    The distance is OpenCV's ``HISTCMP_CHISQR_ALT`` over normalised histograms,
    ``2 * sum((p - q)^2 / (p + q))``: 0 for the same histogram, 4 for disjoint ones. That is twice
    the :attr:`SceneChangeMetadata.distance` of the ``scene_change`` detector, which does the
    work; the summary gives the ``chisqr_alt`` value. A camera's first frame is only remembered.

    Raises:
        ROSConfigError: ``threshold`` outside (0, 4].
    """

    kind = "scene_change"
    metric = "chisqr_alt"
    bins = 32

    def __init__(self, *, threshold: float = 0.5) -> None:
        if not 0 < threshold <= 4:
            raise ROSConfigError(f"{threshold} is not a chisqr_alt distance in (0, 4]", field="threshold")
        self.threshold = threshold
        self._histograms = SceneChangeDetector(SceneChangeParams(threshold=threshold / 2, bins=self.bins))

    def detect_frame(self, frame: DetectorFrame) -> SceneChangeMetadata | None:
        """A scene change against this camera's previous frame (``None`` within the threshold, or for its first)."""
        return self._histograms.detect(frame)

    def summarise(self, metadata: SceneChangeMetadata) -> str:
        return (
            f"scene changed ({self.metric} {2 * metadata.distance:.2f}; mean grey "
            f"{metadata.mean_grey_before:.0f} -> {metadata.mean_grey_after:.0f})"
        )
