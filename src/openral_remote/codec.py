"""The wire format of observations and chunks: named fields, arrays as dtype + shape + bytes, never pickle.

A message is ``b"ORW1"``, a 4-byte little-endian header length, a UTF-8 JSON header, then the
arrays' bytes back to back. The header names every field: an array (``dtype``, ``shape``, its
``offset`` and ``nbytes`` in the payload), a JPEG image (for slow links: ``offset``, ``nbytes``), or
a plain JSON value (numbers, text, lists). Decoding trusts nothing: the magic, the header's size and
shape, every dtype (numbers and booleans only: object, void and text arrays are refused, so nothing
can smuggle code or pointers), and that every array lies inside the payload and has exactly the
bytes its shape needs. Arrays are decoded as read-only views of the message, without a copy.
Multi-byte numbers travel little-endian whatever the sender's byte order.

Any input either decodes or raises :class:`WireFormatError`: integers are checked to be integers
(``true`` is not a dimension), sizes are computed without overflow and bounded by what an array
can address, and a header nested too deeply or holding numbers too long to parse is refused.
"""

from __future__ import annotations

import io
import json
import math
import struct
from collections.abc import Mapping
from typing import Any, Final, TypeGuard

import numpy as np

from openral_core import ROSRuntimeError

MAGIC: Final = b"ORW1"
SCHEMA_VERSION: Final = 1
MAX_HEADER_BYTES: Final = 1 << 20
MAX_DIMS: Final = 8
ALLOWED_DTYPES: Final = frozenset(
    {"bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float16", "float32", "float64"}
)
"""Array element types accepted on the wire: numbers and booleans, nothing that can hold an object."""

_PREFIX = struct.Struct("<4sI")
_MAX_ARRAY_BYTES: Final = np.iinfo(np.intp).max
"""What one array may span, zero-size dimensions aside (numpy's own limit)."""


class WireFormatError(ROSRuntimeError):
    """A message that is not a well-formed openral wire message (or asks for what the codec refuses)."""


def encode(fields: Mapping[str, Any], *, jpeg: Mapping[str, int] | None = None) -> bytes:
    """One message holding ``fields``.

    Args:
        fields: Name → numpy array (numeric or boolean), or a JSON value (number, text, bool,
            ``None``, lists and mappings of those).
        jpeg: Name → quality (1–95) of ``uint8`` ``(H, W, 3)`` RGB arrays to send as JPEG instead
            of raw pixels (smaller, lossy; for slow links).

    Raises:
        WireFormatError: An array of a refused dtype, or a value JSON cannot carry.
    """
    header: dict[str, Any] = {"version": SCHEMA_VERSION, "fields": {}}
    blobs: list[bytes | memoryview] = []
    offset = 0
    for name, value in fields.items():
        if isinstance(value, np.ndarray):
            if jpeg is not None and name in jpeg:
                blob: bytes | memoryview = _jpeg_bytes(name, value, jpeg[name])
                entry: dict[str, Any] = {"kind": "jpeg", "shape": list(value.shape)}
            else:
                dtype = value.dtype.name
                if dtype not in ALLOWED_DTYPES:
                    raise WireFormatError(
                        f"field {name!r}: arrays of {dtype} cannot be sent (numbers and booleans only)"
                    )
                # Little-endian and C order; a flat view casts to bytes even with a zero-size dimension.
                array = np.asarray(value, dtype=value.dtype.newbyteorder("<"), order="C")
                blob = array.reshape(-1).data.cast("B")
                entry = {"kind": "array", "dtype": dtype, "shape": list(value.shape)}
            entry.update(offset=offset, nbytes=len(blob))
            blobs.append(blob)
            offset += len(blob)
        else:
            entry = {"kind": "value", "value": _plain(name, value)}
        header["fields"][name] = entry
    text = json.dumps(header, separators=(",", ":"), allow_nan=True).encode("utf-8")
    return b"".join([_PREFIX.pack(MAGIC, len(text)), text, *blobs])


def decode(message: bytes | bytearray | memoryview) -> dict[str, Any]:
    """The fields of a message: arrays as read-only views of it, images decoded, values as JSON gave them.

    Raises:
        WireFormatError: Anything malformed or refused, naming what.
    """
    entries, payload = _split(message)
    return {name: _field(name, entry, payload) for name, entry in entries.items()}


def read_header(message: bytes | bytearray | memoryview) -> dict[str, Any]:
    """The field table of a message (name → entry: ``kind``, ``shape``, ``dtype``, ``nbytes``), nothing decoded.

    What a server checks a request against before it spends anything on it (a JPEG's pixels).

    Raises:
        WireFormatError: The prefix or the header is malformed.
    """
    return _split(message)[0]


def _split(message: bytes | bytearray | memoryview) -> tuple[dict[str, Any], memoryview]:
    """The checked field table and the payload after it."""
    view = memoryview(message).cast("B")
    if len(view) < _PREFIX.size:
        raise WireFormatError(f"a message of {len(view)} bytes is shorter than its prefix")
    magic, header_len = _PREFIX.unpack_from(view)
    if magic != MAGIC:
        raise WireFormatError(f"not an openral wire message (magic {bytes(magic)!r})")
    if header_len > MAX_HEADER_BYTES or _PREFIX.size + header_len > len(view):
        raise WireFormatError(f"header of {header_len} bytes does not fit the message or the limit")
    try:
        header = json.loads(bytes(view[_PREFIX.size : _PREFIX.size + header_len]).decode("utf-8"))
    except ValueError as exc:  # not UTF-8, not JSON, or an integer too long to convert
        raise WireFormatError(f"header is not JSON: {exc}") from None
    except RecursionError:
        raise WireFormatError("header is nested too deeply") from None
    version = header.get("version") if isinstance(header, dict) else None
    if not _is_int(version) or version != SCHEMA_VERSION:
        raise WireFormatError(f"unsupported message version {version!r}")
    entries = header.get("fields")
    if not isinstance(entries, dict):
        raise WireFormatError("header has no field table")
    return entries, view[_PREFIX.size + header_len :]


def _field(name: str, entry: Any, payload: memoryview) -> Any:
    if not isinstance(entry, dict):
        raise WireFormatError(f"field {name!r}: malformed entry")
    kind = entry.get("kind")
    if kind == "value":
        return entry.get("value")
    blob = _blob(name, entry, payload)
    shape = entry.get("shape")
    if not isinstance(shape, list) or len(shape) > MAX_DIMS or not all(_is_int(d) and d >= 0 for d in shape):
        raise WireFormatError(f"field {name!r}: bad shape {_brief(shape)}")
    if kind == "jpeg":
        return _from_jpeg(name, blob, shape)
    if kind != "array":
        raise WireFormatError(f"field {name!r}: unknown kind {_brief(kind)}")
    dtype = entry.get("dtype")
    if not isinstance(dtype, str) or dtype not in ALLOWED_DTYPES:
        raise WireFormatError(f"field {name!r}: dtype {_brief(dtype)} is refused (numbers and booleans only)")
    wire_dtype = np.dtype(dtype).newbyteorder("<")
    # Python integers: no product wraps. Zero-size dimensions aside, numpy caps an array's bytes.
    if math.prod(d for d in shape if d) * wire_dtype.itemsize > _MAX_ARRAY_BYTES:
        raise WireFormatError(f"field {name!r}: shape {_brief(shape)} is larger than any array")
    if math.prod(shape) * wire_dtype.itemsize != len(blob):
        raise WireFormatError(f"field {name!r}: {len(blob)} bytes for shape {_brief(shape)} of {dtype}")
    array = np.frombuffer(blob, dtype=wire_dtype).reshape(shape)
    array.flags.writeable = False
    return array


def _is_int(value: Any) -> TypeGuard[int]:
    """A JSON integer (``true`` and ``false`` are not)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _brief(value: Any) -> str:
    """``repr(value)`` cut short: error messages quote hostile input, so they bound it."""
    text = repr(value)
    return text if len(text) <= 80 else f"{text[:77]}..."


def _blob(name: str, entry: dict[str, Any], payload: memoryview) -> memoryview:
    offset, nbytes = entry.get("offset"), entry.get("nbytes")
    if not (_is_int(offset) and _is_int(nbytes)) or offset < 0 or nbytes < 0:
        raise WireFormatError(f"field {name!r}: bad offset or size")
    if offset + nbytes > len(payload):
        raise WireFormatError(
            f"field {name!r}: {_brief(nbytes)} bytes at offset {_brief(offset)} lie outside "
            f"the {len(payload)}-byte payload"
        )
    return payload[offset : offset + nbytes]


_SCALARS: Final = frozenset({int, float, str, bool, type(None)})
"""Values JSON always carries (``allow_nan``): nothing to check."""


def _plain(name: str, value: Any) -> Any:
    if type(value) in _SCALARS:
        return value
    try:
        json.dumps(value, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise WireFormatError(f"field {name!r}: {type(value).__name__} is neither an array nor a JSON value") from exc
    return value


def _jpeg_bytes(name: str, image: np.ndarray, quality: int) -> bytes:
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise WireFormatError(f"field {name!r}: JPEG takes uint8 (H, W, 3) RGB images, not {image.dtype} {image.shape}")
    from PIL import Image  # noqa: PLC0415

    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(out, format="JPEG", quality=max(1, min(95, quality)))
    return out.getvalue()


def _from_jpeg(name: str, blob: memoryview, shape: list[int]) -> np.ndarray:
    from PIL import Image  # noqa: PLC0415

    if len(shape) != 3 or shape[2] != 3:
        raise WireFormatError(f"field {name!r}: a JPEG image is (H, W, 3), not {_brief(shape)}")
    try:
        with Image.open(io.BytesIO(bytes(blob)), formats=["JPEG"]) as image:
            # The header's size is known before any pixel is decoded: refuse a mismatch first.
            if image.size != (shape[1], shape[0]):
                raise WireFormatError(f"field {name!r}: JPEG of {image.size[::-1]} announced as {_brief(shape)}")
            pixels = np.asarray(image.convert("RGB"))
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise WireFormatError(f"field {name!r}: undecodable JPEG ({exc})") from None
    if list(pixels.shape) != shape:
        raise WireFormatError(f"field {name!r}: JPEG of {list(pixels.shape)} announced as {_brief(shape)}")
    return pixels
