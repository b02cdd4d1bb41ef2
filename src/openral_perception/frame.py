"""``DetectorFrame``: one camera frame as every detector sees it, its colour and grey forms made once.

The publisher wraps each frame once and hands the same view to every detector, so the grey image
that motion and scene change both read is computed once, and colour order is turned by the
frame's own :class:`~openral_core.SensorFrame` views (``as_bgr``, ``as_rgb``, ``as_grey``), never
by a detector. Detectors read the arrays and never write to them: they may be views of the
capture buffer, shared with the skill and with the other detectors.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from openral_core import FrameEncoding, SensorFrame

VIEWABLE: Final = frozenset(
    {FrameEncoding.BGR8, FrameEncoding.RGB8, FrameEncoding.BGRA8, FrameEncoding.RGBA8, FrameEncoding.MONO8}
)
"""Encodings a detector can look at: 8-bit colour or grey held inline (not compressed, not 16-bit depth)."""


def is_viewable(frame: SensorFrame) -> bool:
    """Whether ``frame`` carries pixels a detector can look at (see :data:`VIEWABLE`)."""
    return frame.data is not None and frame.encoding in VIEWABLE


class DetectorFrame:
    """A read-only view of one :class:`~openral_core.SensorFrame` with its BGR, RGB and grey forms cached.

    Each form is made on first use and kept, so however many detectors read it, a frame is turned
    grey once. The colour forms are views of the capture buffer (no copy); grey is one new array
    for a colour frame (BT.601 luma) and a view for a grey one.

    Raises:
        ValueError: The frame has no pixels a detector can look at (see :func:`is_viewable`).
    """

    __slots__ = ("_bgr", "_frame", "_grey", "_rgb")

    def __init__(self, frame: SensorFrame) -> None:
        if not is_viewable(frame):
            raise ValueError(
                f"frame '{frame.sensor_id}' is {frame.encoding.value}"
                f"{'' if frame.data is not None else ' without inline data'}; detectors look at "
                f"{', '.join(sorted(e.value for e in VIEWABLE))} frames"
            )
        self._frame = frame
        self._bgr: np.ndarray | None = None
        self._rgb: np.ndarray | None = None
        self._grey: np.ndarray | None = None

    @classmethod
    def from_array(
        cls, pixels: np.ndarray, *, sensor_id: str, stamp_ns: int = 0, encoding: FrameEncoding | None = None
    ) -> DetectorFrame:
        """A view of an ``(H, W, 3)`` BGR (or given ``encoding``) or ``(H, W)`` grey uint8 array, not copied.

        Raises:
            ValueError: Not a uint8 array of one of those shapes.
        """
        if pixels.dtype != np.uint8 or pixels.ndim not in (2, 3):
            raise ValueError(f"expected an (H, W, 3) or (H, W) uint8 array, got {pixels.dtype} {pixels.shape}")
        if encoding is None:
            encoding = FrameEncoding.MONO8 if pixels.ndim == 2 else FrameEncoding.BGR8
        height, width = pixels.shape[:2]
        return cls(
            SensorFrame(
                sensor_id=sensor_id, stamp_ns=stamp_ns, width=width, height=height, encoding=encoding, data=pixels
            )
        )

    @property
    def frame(self) -> SensorFrame:
        """The frame this view is of."""
        return self._frame

    @property
    def sensor_id(self) -> str:
        return self._frame.sensor_id

    @property
    def stamp_ns(self) -> int:
        """Capture time (monotonic clock)."""
        return self._frame.stamp_ns

    @property
    def width(self) -> int:
        return self._frame.width

    @property
    def height(self) -> int:
        return self._frame.height

    @property
    def bgr(self) -> np.ndarray:
        """``(H, W, 3)`` uint8 in BGR order (the OpenCV order), made once."""
        if self._bgr is None:
            self._bgr = self._frame.as_bgr()
        return self._bgr

    @property
    def rgb(self) -> np.ndarray:
        """``(H, W, 3)`` uint8 in RGB order (what most models are trained on), made once."""
        if self._rgb is None:
            self._rgb = self._frame.as_rgb()
        return self._rgb

    @property
    def grey(self) -> np.ndarray:
        """``(H, W)`` uint8 BT.601 luma, made once."""
        if self._grey is None:
            self._grey = self._frame.as_grey()
        return self._grey

    def __repr__(self) -> str:
        frame = self._frame
        return f"DetectorFrame({frame.sensor_id!r}, {frame.width}x{frame.height} {frame.encoding.value})"
