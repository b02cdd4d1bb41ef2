"""SensorFrame: one payload, size checks, base64 JSON, and zero-copy numpy views."""

from __future__ import annotations

import base64
import json
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from openral_core import FrameEncoding, SensorFrame

PROPERTY = settings(max_examples=80, deadline=None)
RAW_ENCODINGS = [e for e in FrameEncoding if e not in (FrameEncoding.JPEG, FrameEncoding.PNG)]
ITEM_BYTES = {
    FrameEncoding.RGB8: 3,
    FrameEncoding.BGR8: 3,
    FrameEncoding.RGBA8: 4,
    FrameEncoding.BGRA8: 4,
    FrameEncoding.MONO8: 1,
    FrameEncoding.MONO16: 2,
}


@st.composite
def frames(draw: st.DrawFn) -> SensorFrame:
    """Any valid frame: raw or compressed inline data (any buffer type), or a topic/handle reference."""
    encoding = draw(st.sampled_from(list(FrameEncoding)))
    width = draw(st.integers(1, 6))
    height = draw(st.integers(1, 6))
    common: dict[str, Any] = {
        "sensor_id": draw(st.text(min_size=1, max_size=12)),
        "stamp_ns": draw(st.integers(0, 2**63 - 1)),
        "width": width,
        "height": height,
        "encoding": encoding,
        "seq": draw(st.integers(0, 2**40)),
        "frame_id": draw(st.none() | st.text(max_size=12)),
    }
    payload = draw(st.sampled_from(["data", "data", "topic", "handle"]))
    if payload == "topic":
        return SensorFrame(**common, topic=draw(st.text(max_size=20)))
    if payload == "handle":
        return SensorFrame(**common, handle=draw(st.text(max_size=20)))
    stride = None
    if encoding in ITEM_BYTES:
        packed = width * ITEM_BYTES[encoding]
        stride = draw(st.none() | st.integers(packed, packed + 8))
        need = height * (stride or packed)
        raw = draw(st.binary(min_size=need, max_size=need + 8))
    else:
        raw = draw(st.binary(max_size=40))
    kind = draw(st.sampled_from(["bytes", "bytearray", "memoryview", "ndarray"]))
    data: Any = {
        "bytes": raw,
        "bytearray": bytearray(raw),
        "memoryview": memoryview(raw),
        "ndarray": np.frombuffer(raw, np.uint8),
    }[kind]
    return SensorFrame(**common, row_stride=stride, data=data)


def _frame(**overrides: Any) -> SensorFrame:
    fields: dict[str, Any] = {"sensor_id": "cam", "stamp_ns": 5, "width": 2, "height": 2, "data": bytes(12)}
    fields.update(overrides)
    return SensorFrame(**fields)


# --- round trips ----------------------------------------------------------------------------------


@PROPERTY
@given(frames())
def test_json_round_trip(frame: SensorFrame) -> None:
    assert SensorFrame.model_validate_json(frame.model_dump_json()) == frame


@PROPERTY
@given(frames())
def test_python_round_trip(frame: SensorFrame) -> None:
    assert SensorFrame.model_validate(frame.model_dump()) == frame


def test_data_is_base64_text_in_json() -> None:
    raw = bytes(range(12))
    dumped = json.loads(_frame(data=memoryview(raw)).model_dump_json())
    assert dumped["data"] == base64.b64encode(raw).decode("ascii")
    assert dumped["topic"] is None


def test_invalid_base64_in_json_is_rejected() -> None:
    text = json.dumps({"sensor_id": "cam", "stamp_ns": 0, "width": 1, "height": 1, "data": "not base64!"})
    with pytest.raises(ValidationError, match="base64"):
        SensorFrame.model_validate_json(text)


def test_frames_with_different_pixels_are_not_equal() -> None:
    assert _frame(data=bytes(12)) != _frame(data=bytes(11) + b"\x01")
    assert _frame(data=bytearray(12)) == _frame(data=np.zeros(12, np.uint8))
    assert _frame(data=bytes(12)) != _frame(data=None, topic="/cam")


@pytest.mark.parametrize("source", ["python", "json"])
def test_unsupported_buffer_type_is_a_validation_error(source: str) -> None:
    def build() -> SensorFrame:
        if source == "python":
            return _frame(data=[0] * 12)
        return SensorFrame.model_validate_json('{"sensor_id": "c", "stamp_ns": 0, "width": 1, "height": 1, "data": 7}')

    with pytest.raises((ValidationError, TypeError)) as info:
        build()
    assert isinstance(info.value, ValidationError), (
        f"a wrong data type escapes as a bare {type(info.value).__name__} ({info.value}); pydantic wraps only "
        "ValueError/AssertionError, so callers (and config loading) never see a ValidationError: "
        "_validate_buffer should raise ValueError"
    )
    assert "frame data must be" in str(info.value)


# --- payload rules --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "payload",
    [
        {},
        {"data": bytes(12), "topic": "/cam"},
        {"data": bytes(12), "handle": "nvmm:1"},
        {"topic": "/cam", "handle": "nvmm:1"},
    ],
)
def test_exactly_one_payload(payload: dict[str, Any]) -> None:
    with pytest.raises(ValidationError, match="exactly one of data, topic or handle"):
        SensorFrame(sensor_id="cam", stamp_ns=0, width=2, height=2, **payload)


@pytest.mark.parametrize(
    ("encoding", "width", "height", "stride", "need"),
    [
        (FrameEncoding.BGR8, 4, 3, None, 36),
        (FrameEncoding.RGBA8, 4, 3, None, 48),
        (FrameEncoding.MONO8, 4, 3, None, 12),
        (FrameEncoding.MONO16, 4, 3, None, 24),
        (FrameEncoding.BGR8, 161, 2, 484, 968),
    ],
)
def test_data_shorter_than_the_image_is_rejected(
    encoding: FrameEncoding, width: int, height: int, stride: int | None, need: int
) -> None:
    SensorFrame(
        sensor_id="cam", stamp_ns=0, width=width, height=height, encoding=encoding, row_stride=stride, data=bytes(need)
    )
    with pytest.raises(ValidationError, match=f"holds {need - 1} bytes.*needs {need}"):
        SensorFrame(
            sensor_id="cam",
            stamp_ns=0,
            width=width,
            height=height,
            encoding=encoding,
            row_stride=stride,
            data=bytes(need - 1),
        )


def test_compressed_data_has_no_size_rule() -> None:
    frame = _frame(encoding=FrameEncoding.JPEG, width=640, height=480, data=b"\xff\xd8")
    assert frame.channels == 0
    with pytest.raises(ValueError, match="jpeg-compressed"):
        frame.as_array()


def test_reference_frames_have_no_array() -> None:
    with pytest.raises(ValueError, match="no inline data"):
        _frame(data=None, topic="/cam/image_raw").as_array()
    with pytest.raises(ValueError, match="no inline data"):
        _frame(data=None, handle="nvmm:7").data_bytes()


@pytest.mark.parametrize("field", ["stamp_ns", "seq"])
def test_negative_counters_are_rejected(field: str) -> None:
    with pytest.raises(ValidationError, match=field):
        _frame(**{field: -1})


def test_frame_is_frozen() -> None:
    frame = _frame()
    with pytest.raises(ValidationError, match="frozen"):
        frame.seq = 3  # type: ignore[misc]


def test_age_is_measured_from_the_capture_stamp() -> None:
    assert _frame(stamp_ns=1_000_000).age_ms(3_500_000) == 2.5


# --- zero-copy views ------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["bytes", "bytearray", "memoryview", "ndarray-flat", "ndarray-hwc"])
def test_as_array_is_a_view_of_the_capture_buffer(kind: str) -> None:
    pixels = np.arange(3 * 4 * 3, dtype=np.uint8).reshape(3, 4, 3)
    raw = pixels.tobytes()
    buffers: dict[str, Any] = {
        "bytes": raw,
        "bytearray": bytearray(raw),
        "memoryview": memoryview(bytearray(raw)),
        "ndarray-flat": pixels.copy().reshape(-1),
        "ndarray-hwc": pixels.copy(),
    }
    buffer = buffers[kind]
    frame = SensorFrame(sensor_id="cam", stamp_ns=0, width=4, height=3, data=buffer)
    view = frame.as_array()
    assert frame.data is buffer, "the frame must keep the capture buffer itself"
    assert view.shape == (3, 4, 3)
    assert view.dtype == np.uint8
    np.testing.assert_array_equal(view, pixels)
    base = buffer if isinstance(buffer, np.ndarray) else np.frombuffer(buffer, np.uint8)
    assert np.shares_memory(view, base), f"as_array copied a {kind} buffer"


def test_row_stride_padding_is_skipped_for_odd_widths() -> None:
    width, height = 161, 3
    stride = (width * 3 + 3) // 4 * 4  # GStreamer pads rows to 4 bytes: 483 -> 484
    assert stride == 484
    rng = np.random.default_rng(0)
    pixels = rng.integers(0, 255, size=(height, width, 3), dtype=np.uint8)
    padded = np.full((height, stride), 0xEE, np.uint8)
    padded[:, : width * 3] = pixels.reshape(height, width * 3)
    raw = padded.tobytes()
    frame = SensorFrame(sensor_id="cam", stamp_ns=0, width=width, height=height, row_stride=stride, data=raw)
    view = frame.as_array()
    assert view.shape == (height, width, 3)
    np.testing.assert_array_equal(view, pixels)
    assert np.shares_memory(view, np.frombuffer(raw, np.uint8))


@PROPERTY
@given(
    encoding=st.sampled_from(RAW_ENCODINGS),
    width=st.integers(1, 9),
    height=st.integers(1, 5),
    pad=st.integers(0, 7),
    seed=st.integers(0, 2**32 - 1),
)
def test_as_array_matches_the_packed_pixels_for_any_padding(
    encoding: FrameEncoding, width: int, height: int, pad: int, seed: int
) -> None:
    item = ITEM_BYTES[encoding]
    stride = width * item + pad
    rng = np.random.default_rng(seed)
    padded = rng.integers(0, 256, size=(height, stride), dtype=np.uint8)
    frame = SensorFrame(
        sensor_id="cam",
        stamp_ns=0,
        width=width,
        height=height,
        encoding=encoding,
        row_stride=stride if pad else None,
        data=bytearray(padded.tobytes()),
    )
    expected = np.ascontiguousarray(padded[:, : width * item])
    dtype = np.uint16 if encoding is FrameEncoding.MONO16 else np.uint8
    channels = item // np.dtype(dtype).itemsize
    expected_pixels = expected.view(dtype).reshape(height, width, channels)
    if channels == 1:
        expected_pixels = expected_pixels[:, :, 0]
    view = frame.as_array()
    assert view.dtype == dtype
    np.testing.assert_array_equal(view, expected_pixels)


def test_mono8_and_mono16_are_two_dimensional() -> None:
    mono8 = SensorFrame(sensor_id="c", stamp_ns=0, width=3, height=2, encoding=FrameEncoding.MONO8, data=bytes(6))
    assert mono8.as_array().shape == (2, 3)
    values = np.array([[1, 2, 3], [256, 1000, 65535]], np.uint16)
    mono16 = SensorFrame(
        sensor_id="c", stamp_ns=0, width=3, height=2, encoding=FrameEncoding.MONO16, data=values.tobytes()
    )
    view = mono16.as_array()
    assert view.shape == (2, 3)
    assert view.dtype == np.uint16
    np.testing.assert_array_equal(view, values)
    assert mono16.bytes_per_channel == 2
    assert mono16.channels == 1


def test_mono8_array_with_a_channel_axis_is_still_two_dimensional() -> None:
    image = np.arange(6, dtype=np.uint8).reshape(2, 3, 1)
    frame = SensorFrame(sensor_id="c", stamp_ns=0, width=3, height=2, encoding=FrameEncoding.MONO8, data=image)
    assert frame.as_array().shape == (2, 3), (
        "as_array() of a mono frame must be (H, W) whatever the buffer's shape: an (H, W, 1) capture array "
        "is returned as is, so skills see (H, W) from one backend and (H, W, 1) from another"
    )


def test_non_contiguous_flat_array_gives_the_right_pixels() -> None:
    pixels = np.arange(2 * 3 * 3, dtype=np.uint8)
    every_other = np.repeat(pixels, 2)[::2]  # a strided view holding exactly these values
    np.testing.assert_array_equal(every_other, pixels)
    frame = SensorFrame(sensor_id="c", stamp_ns=0, width=3, height=2, data=every_other)
    np.testing.assert_array_equal(
        frame.as_array(),
        pixels.reshape(2, 3, 3),
        err_msg="as_array() read a strided (non-contiguous) buffer as if it were packed: wrong pixels",
    )


def test_array_view_over_bytes_is_read_only() -> None:
    view = _frame(data=bytes(12)).as_array()
    assert not view.flags.writeable
    with pytest.raises(ValueError, match="read-only"):
        view[0, 0, 0] = 1


def test_data_bytes_copies_only_when_needed() -> None:
    raw = bytes(range(12))
    assert _frame(data=raw).data_bytes() is raw
    assert _frame(data=np.frombuffer(raw, np.uint8)).data_bytes() == raw


# -- colour views ----------------------------------------------------------------------


def _colour_frame(encoding: FrameEncoding, pixels: np.ndarray) -> SensorFrame:
    return SensorFrame(
        sensor_id="cam", stamp_ns=1, width=pixels.shape[1], height=pixels.shape[0], encoding=encoding, data=pixels
    )


@pytest.mark.parametrize(
    ("encoding", "first_pixel"),
    [
        (FrameEncoding.RGB8, [10, 20, 30]),
        (FrameEncoding.BGR8, [30, 20, 10]),
        (FrameEncoding.RGBA8, [10, 20, 30, 255]),
        (FrameEncoding.BGRA8, [30, 20, 10, 255]),
    ],
)
def test_colour_views_agree_on_every_encoding_without_copying(encoding: FrameEncoding, first_pixel: list[int]) -> None:
    pixels = np.zeros((4, 6, len(first_pixel)), np.uint8)
    pixels[0, 0] = first_pixel
    frame = _colour_frame(encoding, pixels)
    assert frame.as_rgb()[0, 0].tolist() == [10, 20, 30]
    assert frame.as_bgr()[0, 0].tolist() == [30, 20, 10]
    assert np.shares_memory(frame.as_rgb(), pixels)
    assert np.shares_memory(frame.as_bgr(), pixels)
    assert frame.as_rgb().shape == frame.as_bgr().shape == (4, 6, 3)


def test_grey_is_bt601_luma_of_colour_and_a_view_of_grey() -> None:
    colour = np.zeros((2, 2, 3), np.uint8)
    colour[0, 0] = [255, 0, 0]  # pure red in RGB
    colour[0, 1] = [255, 255, 255]
    grey = _colour_frame(FrameEncoding.RGB8, colour).as_grey()
    assert grey.shape == (2, 2)
    assert grey.dtype == np.uint8
    assert grey[0, 0] == (255 * 77 + 128) >> 8
    assert grey[0, 1] == 255
    assert grey[1, 1] == 0
    assert np.array_equal(_colour_frame(FrameEncoding.BGR8, colour[..., ::-1].copy()).as_grey(), grey)
    mono = np.arange(12, dtype=np.uint8).reshape(3, 4)
    mono_frame = _colour_frame(FrameEncoding.MONO8, mono)
    assert np.shares_memory(mono_frame.as_grey(), mono)
    rgb = mono_frame.as_rgb()
    assert rgb.shape == (3, 4, 3)
    assert np.array_equal(rgb[..., 2], mono)
    assert np.shares_memory(rgb, mono)


def test_colour_views_refuse_what_has_no_8bit_colour() -> None:
    depth = SensorFrame(sensor_id="depth", stamp_ns=1, width=2, height=2, encoding=FrameEncoding.MONO16, data=bytes(8))
    with pytest.raises(ValueError, match="16-bit"):
        depth.as_rgb()
    jpeg = SensorFrame(sensor_id="cam", stamp_ns=1, width=2, height=2, encoding=FrameEncoding.JPEG, data=b"\xff\xd8")
    with pytest.raises(ValueError, match="compressed"):
        jpeg.as_bgr()
