"""Sensor frames: the carrier from a capture backend to the skill, without copying pixels."""

from __future__ import annotations

import base64
import binascii
from enum import StrEnum
from typing import Annotated, Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PlainSerializer, PlainValidator, model_validator


class FrameEncoding(StrEnum):
    """Pixel layout of a frame's buffer (ROS ``sensor_msgs/Image`` encoding names)."""

    RGB8 = "rgb8"
    BGR8 = "bgr8"
    RGBA8 = "rgba8"
    BGRA8 = "bgra8"
    MONO8 = "mono8"
    MONO16 = "mono16"
    JPEG = "jpeg"
    PNG = "png"


_CHANNELS: dict[FrameEncoding, int] = {
    FrameEncoding.RGB8: 3,
    FrameEncoding.BGR8: 3,
    FrameEncoding.RGBA8: 4,
    FrameEncoding.BGRA8: 4,
    FrameEncoding.MONO8: 1,
    FrameEncoding.MONO16: 1,
}
_COMPRESSED = frozenset({FrameEncoding.JPEG, FrameEncoding.PNG})
# Channel slices that put a colour frame's pixels in RGB or BGR order without copying.
_RGB_ORDER: dict[FrameEncoding, slice] = {
    FrameEncoding.RGB8: slice(0, 3),
    FrameEncoding.RGBA8: slice(0, 3),
    FrameEncoding.BGR8: slice(2, None, -1),
    FrameEncoding.BGRA8: slice(2, None, -1),
}
_BGR_ORDER: dict[FrameEncoding, slice] = {
    FrameEncoding.BGR8: slice(0, 3),
    FrameEncoding.BGRA8: slice(0, 3),
    FrameEncoding.RGB8: slice(2, None, -1),
    FrameEncoding.RGBA8: slice(2, None, -1),
}

FrameBufferType = bytes | bytearray | memoryview | np.ndarray


def _validate_buffer(value: Any) -> FrameBufferType | None:
    """Accept a raw buffer as is (no copy) or decode base64 text coming from JSON."""
    if value is None or isinstance(value, bytes | bytearray | memoryview | np.ndarray):
        return value
    if isinstance(value, str):
        try:
            return base64.b64decode(value.encode("ascii"), validate=True)
        except (binascii.Error, ValueError) as exc:
            raise ValueError("frame data in JSON must be base64 text") from exc
    raise ValueError(f"frame data must be bytes, memoryview, numpy array or base64 text, not {type(value).__name__}")


def _serialize_buffer(value: FrameBufferType | None) -> str | None:
    if value is None:
        return None
    return base64.b64encode(_buffer_bytes(value)).decode("ascii")


def _buffer_bytes(value: FrameBufferType) -> bytes:
    if isinstance(value, bytes):
        return value
    if isinstance(value, np.ndarray):
        return np.ascontiguousarray(value).tobytes()
    return bytes(value)


FrameBuffer = Annotated[
    FrameBufferType | None,
    PlainValidator(_validate_buffer),
    PlainSerializer(_serialize_buffer, when_used="json"),
]


class SensorFrame(BaseModel):
    """One captured image and where it came from.

    Exactly one of ``data`` (the pixels, inline), ``topic`` (a ROS topic that carries
    them) or ``handle`` (an opaque device-memory handle) is set. ``data`` keeps the
    capture buffer itself: :meth:`as_array` returns a numpy view of it, never a copy.
    In JSON, ``data`` is base64 text.

    Attributes:
        stamp_ns: Capture time on the monotonic clock (``time.monotonic_ns``); staleness is
            measured from here, not from arrival.
        seq: Per-sensor frame counter, increasing by one per captured frame.
        row_stride: Bytes per row in ``data`` when rows are padded; ``None`` means tightly packed.
    """

    model_config = ConfigDict(arbitrary_types_allowed=True, frozen=True, extra="forbid")

    sensor_id: str = Field(min_length=1)
    stamp_ns: int = Field(ge=0)
    width: int = Field(ge=1)
    height: int = Field(ge=1)
    encoding: FrameEncoding = FrameEncoding.BGR8
    seq: int = Field(default=0, ge=0)
    frame_id: str | None = None
    row_stride: int | None = Field(default=None, ge=1)
    data: FrameBuffer = None
    topic: str | None = None
    handle: str | None = None

    @model_validator(mode="after")
    def _exactly_one_payload(self) -> Self:
        present = [name for name in ("data", "topic", "handle") if getattr(self, name) is not None]
        if len(present) != 1:
            raise ValueError(f"exactly one of data, topic or handle must be set, got {present or 'none'}")
        if self.data is not None and self.encoding not in _COMPRESSED:
            need = self.height * (self.row_stride or self.width * self.channels * self.bytes_per_channel)
            have = _nbytes(self.data)
            if have < need:
                raise ValueError(
                    f"frame '{self.sensor_id}' data holds {have} bytes, "
                    f"{self.width}x{self.height} {self.encoding.value} needs {need}"
                )
        return self

    @property
    def channels(self) -> int:
        """Channels per pixel (0 for compressed encodings)."""
        return _CHANNELS.get(self.encoding, 0)

    @property
    def bytes_per_channel(self) -> int:
        """Bytes per channel value."""
        return 2 if self.encoding is FrameEncoding.MONO16 else 1

    def age_ms(self, now_ns: int) -> float:
        """Milliseconds between capture and ``now_ns`` (monotonic clock)."""
        return (now_ns - self.stamp_ns) / 1e6

    def as_array(self) -> np.ndarray:
        """The pixels as an ``(H, W, C)`` (or ``(H, W)``) numpy view over ``data``, without copying.

        Raises:
            ValueError: The frame carries no inline data, or is compressed.
        """
        if self.data is None:
            raise ValueError(f"frame '{self.sensor_id}' has no inline data (topic/handle frame)")
        if self.encoding in _COMPRESSED:
            raise ValueError(f"frame '{self.sensor_id}' is {self.encoding.value}-compressed; decode it first")
        dtype = np.uint16 if self.bytes_per_channel == 2 else np.uint8
        data = self.data
        if (
            isinstance(data, np.ndarray)
            and self.row_stride is None
            and data.dtype == dtype
            and data.shape[:2] == (self.height, self.width)
        ):
            return data[:, :, 0] if self.channels == 1 and data.ndim == 3 else data
        if isinstance(data, np.ndarray):
            # A strided buffer cannot be reinterpreted byte-wise; this is the one case that copies.
            raw = np.ascontiguousarray(data).reshape(-1).view(np.uint8)
        else:
            raw = np.frombuffer(data, np.uint8)
        item = self.channels * self.bytes_per_channel
        view = np.lib.stride_tricks.as_strided(
            raw,
            shape=(self.height, self.width, item),
            strides=(self.row_stride or self.width * item, item, 1),
            writeable=False,
        ).view(dtype)
        return view[:, :, 0] if self.channels == 1 else view

    def as_rgb(self) -> np.ndarray:
        """The pixels as ``(H, W, 3)`` uint8 RGB: a view (channels reordered by strides, grey broadcast), never a copy.

        Raises:
            ValueError: No inline data, compressed, or 16-bit grey (no 8-bit colour to show).
        """
        return self._colour_view(_RGB_ORDER)

    def as_bgr(self) -> np.ndarray:
        """The pixels as ``(H, W, 3)`` uint8 BGR (the OpenCV order): a view, never a copy.

        Raises:
            ValueError: No inline data, compressed, or 16-bit grey.
        """
        return self._colour_view(_BGR_ORDER)

    def as_grey(self) -> np.ndarray:
        """The pixels as ``(H, W)`` uint8 grey: a view of a grey frame, BT.601 luma (one new array) of a colour one.

        The luma uses integer weights summing to 256 (29 B, 150 G, 77 R), so no level can wrap.

        Raises:
            ValueError: No inline data, compressed, or 16-bit grey.
        """
        if self.encoding is FrameEncoding.MONO8:
            return self.as_array()
        bgr = self.as_bgr()
        pixels = bgr.astype(np.uint32)
        weighted = pixels[..., 0] * 29 + pixels[..., 1] * 150 + pixels[..., 2] * 77 + 128
        return (weighted >> 8).astype(np.uint8)

    def _colour_view(self, order: dict[FrameEncoding, slice]) -> np.ndarray:
        if self.encoding is FrameEncoding.MONO16:
            raise ValueError(f"frame '{self.sensor_id}' is 16-bit grey (depth); it has no 8-bit colour view")
        pixels = self.as_array()
        if self.encoding is FrameEncoding.MONO8:
            return np.broadcast_to(pixels[:, :, None], (self.height, self.width, 3))
        return pixels[:, :, order[self.encoding]]

    def data_bytes(self) -> bytes:
        """The inline payload as ``bytes`` (copies unless it already is ``bytes``)."""
        if self.data is None:
            raise ValueError(f"frame '{self.sensor_id}' has no inline data")
        return _buffer_bytes(self.data)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SensorFrame):
            return NotImplemented
        mine = self.model_dump(exclude={"data"})
        theirs = other.model_dump(exclude={"data"})
        if mine != theirs:
            return False
        if self.data is None or other.data is None:
            return self.data is other.data
        return _buffer_bytes(self.data) == _buffer_bytes(other.data)

    __hash__ = None  # type: ignore[assignment]


def _nbytes(buffer: FrameBufferType) -> int:
    if isinstance(buffer, np.ndarray):
        return int(buffer.nbytes)
    if isinstance(buffer, memoryview):
        return buffer.nbytes
    return len(buffer)
