"""The wire codec: what goes in comes out, and nothing malformed or dangerous is ever decoded."""

from __future__ import annotations

import json
import pickle
import struct

import numpy as np
import pytest

from openral_remote.codec import MAGIC, WireFormatError, decode, encode


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


def _message(header: dict[str, object], payload: bytes = b"") -> bytes:
    text = json.dumps(header).encode()
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
