"""The wire codec: what goes in comes out, and nothing malformed or dangerous is ever decoded."""

from __future__ import annotations

import json
import pickle
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as npst

from openral_remote.codec import ALLOWED_DTYPES, MAGIC, MAX_DIMS, WireFormatError, decode, encode


def test_arrays_and_values_round_trip_exactly_without_a_copy() -> None:
    image = np.arange(480 * 640 * 3, dtype=np.uint8).reshape(480, 640, 3)
    chunk = np.linspace(-1, 1, 50 * 6, dtype=np.float32).reshape(50, 6)
    message = encode({"image": image, "chunk": chunk, "mask": np.array([True, False]), "tick": 17, "task": "pick"})
    fields = decode(message)
    np.testing.assert_array_equal(fields["image"], image)
    np.testing.assert_array_equal(fields["chunk"], chunk)
    assert fields["chunk"].dtype == np.float32
    assert fields["mask"].tolist() == [True, False]
    assert (fields["tick"], fields["task"]) == (17, "pick")
    assert not fields["image"].flags.writeable  # a view of the message, read-only
    assert len(message) < image.nbytes + chunk.nbytes + 400


def test_jpeg_images_are_smaller_and_close() -> None:
    rows, cols = np.mgrid[0:96, 0:128]
    image = np.stack([rows * 2, cols * 2, (rows + cols)], axis=2).astype(np.uint8)
    raw = encode({"image": image})
    small = encode({"image": image}, jpeg={"image": 90})
    assert len(small) < len(raw) / 3
    decoded = decode(small)["image"]
    assert decoded.shape == image.shape
    assert np.abs(decoded.astype(int) - image.astype(int)).mean() < 3


@pytest.mark.parametrize("value", [np.array([object()]), np.zeros(2, dtype="V4"), np.array(["text"])])
def test_arrays_that_could_carry_objects_are_refused_on_encode(value: np.ndarray) -> None:
    with pytest.raises(WireFormatError, match="cannot be sent"):
        encode({"x": value})


def test_a_value_json_cannot_carry_is_refused() -> None:
    with pytest.raises(WireFormatError, match="neither an array nor a JSON value"):
        encode({"x": object()})


def _message(header: object, payload: bytes = b"") -> bytes:
    """A message around ``header`` (raw bytes are sent as they are)."""
    text = header if isinstance(header, bytes) else json.dumps(header).encode()
    return struct.pack("<4sI", MAGIC, len(text)) + text + payload


def _one(kind: str, payload: bytes, **entry: object) -> bytes:
    """A message with one field ``x`` of ``kind`` over ``payload``."""
    return _message(
        {"version": 1, "fields": {"x": {"kind": kind, "offset": 0, "nbytes": len(payload), **entry}}}, payload
    )


@pytest.mark.parametrize(
    ("message", "match"),
    [
        (b"ORW", "shorter than its prefix"),
        (pickle.dumps({"x": 1}), "not an openral wire message"),
        (struct.pack("<4sI", MAGIC, 1 << 30) + b"{}", "does not fit"),
        (struct.pack("<4sI", MAGIC, 2) + b"\xff\xfe", "not JSON"),
        (_message({"version": 99, "fields": {}}), "unsupported message version"),
        (_one("array", b"\0" * 8, dtype="object", shape=[1]), "refused"),
        (_one("array", b"\0" * 8, dtype="float32", shape=[4], nbytes=16), "outside"),
        (_one("array", b"\0" * 8, dtype="float32", shape=[3]), "8 bytes for shape"),
        (_one("array", b"\0", dtype="uint8", shape=[-1]), "bad shape"),
        (_one("pickle", b"\0", shape=[1]), "unknown kind"),
        (_one("jpeg", b"\0" * 4, shape=[1, 1, 3]), "JPEG"),
    ],
)
def test_malformed_or_hostile_messages_are_refused_with_the_reason(message: bytes, match: str) -> None:
    with pytest.raises(WireFormatError, match=match):
        decode(message)


def _deep(depth: int) -> bytes:
    return b"[" * depth + b"]" * depth


@pytest.mark.parametrize(
    ("message", "match"),
    [
        (_message(_deep(100_000)), "nested too deeply"),
        (_one("array", b"", dtype="uint8", shape=[2**70]), "larger than any array"),
        (_one("array", b"", dtype="uint8", shape=[2**32, 2**32]), "larger than any array"),  # wraps to 0 in 64 bits
        (_one("array", b"", dtype="uint8", shape=[0, 2**70]), "larger than any array"),
        (_one("array", b"\0", dtype=["uint8"], shape=[1]), "dtype"),
        (_one("array", b"\0", dtype="uint8", shape=[True]), "bad shape"),
        (_one("array", b"\0", dtype="uint8", shape=[1], offset=False), "bad offset"),
        (_message(b'{"version":1,"fields":{"x":{"kind":"value","value":' + b"9" * 5000 + b"}}}"), "not JSON"),
        (_message({"version": True, "fields": {}}), "unsupported message version"),
        (_one("jpeg", b"\0" * 4, shape=[2, 2]), r"\(H, W, 3\)"),
    ],
)
def test_hostile_sizes_types_and_nesting_are_wire_format_errors(message: bytes, match: str) -> None:
    with pytest.raises(WireFormatError, match=match):
        decode(message)


def test_a_jpeg_whose_size_differs_from_its_announced_shape_is_refused_before_decoding() -> None:
    image = np.zeros((16, 24, 3), dtype=np.uint8)
    message = encode({"image": image}, jpeg={"image": 80})
    forged = message.replace(b'"shape":[16,24,3]', b'"shape":[24,16,3]')
    with pytest.raises(WireFormatError, match="announced as"):
        decode(forged)


# -- properties --------------------------------------------------------------------------------

_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**80), 2**80),
    st.sampled_from([2**31, 2**32, 2**63 - 1, 2**63, 2**64, -(2**63)]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
)
_json = st.recursive(
    _scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=16,
)


def _mostly(plausible: st.SearchStrategy[object], hostile: st.SearchStrategy[object]) -> st.SearchStrategy[object]:
    """``plausible`` three times in four, so generated messages get past the first checks to the later ones."""
    return st.sampled_from((False, False, False, True)).flatmap(lambda odd: hostile if odd else plausible)


_dims = _mostly(st.integers(0, 4), st.integers(-2, 2**70) | st.sampled_from([2**31, 2**32, 2**62, 2**64]) | _scalars)
_entries = st.fixed_dictionaries(
    {
        "kind": _mostly(st.sampled_from(["array", "array", "jpeg", "value"]), _scalars),
        "dtype": _mostly(st.sampled_from(sorted(ALLOWED_DTYPES)), st.sampled_from(["object", "V4", "<U1"]) | _json),
        "shape": _mostly(st.lists(_dims, max_size=MAX_DIMS + 2), _json),
        "offset": _mostly(st.integers(0, 4), _dims),
        "nbytes": _mostly(st.integers(0, 16), _dims),
    },
    optional={"value": _json},
)
_headers = st.fixed_dictionaries(
    {
        "version": _mostly(st.just(1), _scalars),
        "fields": _mostly(
            st.dictionaries(st.text(max_size=4), _mostly(_entries, _json), min_size=1, max_size=3), _json
        ),
    }
)


def _decodes_or_refuses(message: bytes) -> None:
    try:
        fields = decode(message)
    except WireFormatError:
        return
    assert isinstance(fields, dict)


@settings(max_examples=500, deadline=None)
@given(header=_headers, payload=st.binary(max_size=96))
def test_any_generated_header_decodes_or_is_a_wire_format_error(header: object, payload: bytes) -> None:
    _decodes_or_refuses(_message(header, payload))


@settings(max_examples=200, deadline=None)
@given(header=_json, payload=st.binary(max_size=16))
def test_any_json_header_decodes_or_is_a_wire_format_error(header: object, payload: bytes) -> None:
    _decodes_or_refuses(_message(header, payload))


@settings(max_examples=300, deadline=None)
@given(header=st.binary(max_size=64), payload=st.binary(max_size=32), length=st.integers(0, 2**32 - 1) | st.none())
def test_any_bytes_decode_or_are_a_wire_format_error(header: bytes, payload: bytes, length: int | None) -> None:
    size = len(header) if length is None else length
    _decodes_or_refuses(struct.pack("<4sI", MAGIC, size) + header + payload)
    _decodes_or_refuses(header + payload)


_wire_dtypes = st.sampled_from(sorted(ALLOWED_DTYPES)).flatmap(
    lambda name: st.sampled_from([np.dtype(name), np.dtype(name).newbyteorder(">")])
)


@settings(max_examples=300, deadline=None)
@given(
    array=npst.arrays(_wire_dtypes, npst.array_shapes(min_dims=0, max_dims=MAX_DIMS, min_side=0, max_side=3)),
    transpose=st.booleans(),
)
def test_any_array_round_trips_zero_size_dimensions_byte_order_and_layout_included(
    array: np.ndarray, transpose: bool
) -> None:
    value = array.T if transpose else array  # a non-contiguous view when it has two or more dimensions
    decoded = decode(encode({"x": value, "n": 3}))
    assert decoded["n"] == 3
    out = decoded["x"]
    assert out.shape == value.shape
    assert out.dtype.name == value.dtype.name
    np.testing.assert_array_equal(out, value)


@pytest.mark.parametrize("shape", [(0, 6), (6, 0), (0,), (), (2, 0, 3)])
def test_empty_and_scalar_arrays_round_trip(shape: tuple[int, ...]) -> None:
    value = np.ones(shape, dtype=np.float32)
    out = decode(encode({"x": value}))["x"]
    assert out.shape == shape
    np.testing.assert_array_equal(out, value)


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_a_corrupted_valid_message_decodes_or_is_a_wire_format_error(data: st.DataObject) -> None:
    message = bytearray(encode({"a": np.arange(6, dtype=np.int16).reshape(2, 3), "t": "pick", "m": np.zeros(0)}))
    for _ in range(data.draw(st.integers(1, 4))):
        index = data.draw(st.integers(0, len(message) - 1))
        message[index] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(message)))
    _decodes_or_refuses(bytes(message[:cut]))
