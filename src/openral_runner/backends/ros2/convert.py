"""``sensor_msgs/Image`` → ``SensorFrame`` without copying pixels, and ROS time → monotonic stamps.

Pure Python: works on any object shaped like a ``sensor_msgs/Image`` message, so it is
tested without a ROS installation.
"""

from __future__ import annotations

from typing import Any, Protocol

from openral_core import FrameEncoding, ROSConfigError, SensorFrame

ROS_ENCODINGS: dict[str, FrameEncoding] = {
    "bgr8": FrameEncoding.BGR8,
    "rgb8": FrameEncoding.RGB8,
    "bgra8": FrameEncoding.BGRA8,
    "rgba8": FrameEncoding.RGBA8,
    "mono8": FrameEncoding.MONO8,
    "8UC1": FrameEncoding.MONO8,
    "mono16": FrameEncoding.MONO16,
    "16UC1": FrameEncoding.MONO16,
}


class _Stamp(Protocol):
    sec: int
    nanosec: int


class _Header(Protocol):
    stamp: _Stamp
    frame_id: str


class ImageMessage(Protocol):
    """The fields of ``sensor_msgs/msg/Image`` this module reads."""

    header: _Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: Any


def stamp_to_ns(stamp: _Stamp) -> int:
    """A ``builtin_interfaces/Time`` as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ros_stamp_to_monotonic_ns(header_stamp_ns: int, *, ros_now_ns: int, monotonic_now_ns: int) -> int:
    """Carry a header stamp onto the monotonic clock, keeping the frame's age.

    Header stamps are on the publisher's ROS clock (usually wall time); staleness here is
    measured on the monotonic clock, so the age ``ros_now - header`` is preserved.
    """
    return monotonic_now_ns - (ros_now_ns - header_stamp_ns)


def image_to_frame(msg: ImageMessage, *, sensor_id: str, stamp_ns: int, seq: int) -> SensorFrame:
    """Wrap the message's pixel buffer as a frame (a memoryview, no copy).

    Raises:
        ROSConfigError: An encoding openral does not carry, or big-endian 16-bit data.
    """
    encoding = ROS_ENCODINGS.get(msg.encoding)
    if encoding is None:
        raise ROSConfigError(
            f"sensor '{sensor_id}' publishes encoding '{msg.encoding}'; supported: {', '.join(ROS_ENCODINGS)}",
            hint="republish as bgr8/rgb8/mono8 (e.g. image_proc) or pick another topic",
        )
    if encoding is FrameEncoding.MONO16 and msg.is_bigendian:
        raise ROSConfigError(f"sensor '{sensor_id}' sends big-endian 16-bit images; only little-endian is supported")
    channels = {FrameEncoding.MONO8: 1, FrameEncoding.MONO16: 1, FrameEncoding.BGRA8: 4, FrameEncoding.RGBA8: 4}
    packed = msg.width * channels.get(encoding, 3) * (2 if encoding is FrameEncoding.MONO16 else 1)
    return SensorFrame(
        sensor_id=sensor_id,
        stamp_ns=stamp_ns,
        width=msg.width,
        height=msg.height,
        encoding=encoding,
        seq=seq,
        frame_id=msg.header.frame_id or None,
        row_stride=msg.step if msg.step != packed else None,
        data=memoryview(msg.data),
    )
