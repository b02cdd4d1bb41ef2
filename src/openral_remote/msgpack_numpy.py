"""msgpack with numpy arrays, in the two dialects the field's policy servers speak.

* ``openpi``: openpi-client's ``msgpack_numpy``. An array is ``{b"__ndarray__": True, b"data",
  b"dtype", b"shape"}`` and a numpy scalar ``{b"__npgeneric__": True, b"data", b"dtype"}``, with
  **bytes** keys. :func:`packb` produces the same bytes as openpi-client's ``packb``.
* ``vla_eval``: vla-eval's protocol codec. An array is ``{"__ndarray__": True, "data", "dtype",
  "shape"}`` with **str** keys, an ``(H, W, 1|3|4)`` ``uint8`` image is
  ``{"__image__": True, "format": "png", "data", "shape"}``, and numpy scalars travel as Python ones.

Decoding trusts nothing: the input's size, the nesting depth and number of entries, only numeric and
boolean dtypes, the number of dimensions and elements of every array, that its bytes are exactly what
its shape needs, and a compressed image's size read from its header before a pixel is decoded.
Nothing is ever unpickled. Anything refused raises :class:`WireFormatError` with a one-line reason.

Decoding has two steps so a server can refuse a request before it spends anything on its arrays:
:func:`unpack_tree` parses the msgpack (arrays still in their encoded form, see
:func:`array_header`), :func:`decode_tree` turns them into numpy arrays.
"""

from __future__ import annotations

import io
import math
import re
from dataclasses import dataclass
from typing import Any, Final, Literal

import msgpack
import numpy as np

from openral_remote.codec import WireFormatError

Dialect = Literal["openpi", "vla_eval"]
DIALECTS: Final[tuple[Dialect, ...]] = ("openpi", "vla_eval")


@dataclass(frozen=True)
class Limits:
    """What one message may hold."""

    max_bytes: int = 64 << 20
    max_depth: int = 32
    max_entries: int = 4096
    """Items of all maps and lists of a message together."""
    max_dims: int = 8
    max_elements: int = 64 << 20
    """Elements of one array (zero-size dimensions aside), or pixels × channels of one image."""


DEFAULT_LIMITS: Final = Limits()

_DTYPE_RE: Final = re.compile(r"[<>|=]?(b1|[iu][1248]|f[248])")
"""Numbers and booleans of at most 8 bytes (no platform-dependent long double)."""

_IMAGE_FORMATS: Final = {"png": "PNG", "jpeg": "JPEG"}
_IMAGE_MODES: Final = {"L": 1, "RGB": 3, "RGBA": 4}


@dataclass(frozen=True)
class ArrayHeader:
    """An encoded array's checked header: what it will decode to, nothing decoded yet."""

    shape: tuple[int, ...]
    dtype: np.dtype[Any]
    image_format: str | None = None
    """``"png"`` or ``"jpeg"`` for a compressed vla-eval image, ``None`` for raw bytes."""


# --- encoding -----------------------------------------------------------------------------------


def packb(obj: Any, *, dialect: Dialect = "openpi", image_format: Literal["png", "raw"] = "png") -> bytes:
    """``obj`` (maps, lists, text, numbers, numpy arrays and scalars) as one message.

    Args:
        obj: What to send.
        dialect: Whose dialect to write.
        image_format: ``vla_eval`` only: how ``(H, W, 1|3|4)`` ``uint8`` arrays travel (vla-eval's
            default is PNG).

    Raises:
        WireFormatError: An array of a refused dtype, or a value msgpack cannot carry.
    """
    default = _openpi_default if dialect == "openpi" else (_vla_png_default if image_format == "png" else _vla_default)
    try:
        return msgpack.packb(obj, default=default)  # type: ignore[no-any-return]
    except (TypeError, ValueError, OverflowError) as exc:
        raise WireFormatError(f"cannot encode: {_brief(exc)}") from None


def _check_dtype(dtype: np.dtype[Any]) -> None:
    if not _DTYPE_RE.fullmatch(dtype.str):
        raise WireFormatError(f"arrays of {dtype} cannot be sent (numbers and booleans only)")


def _openpi_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        _check_dtype(obj.dtype)
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        _check_dtype(obj.dtype)
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"{type(obj).__name__} is not serializable")


def _vla_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        _check_dtype(obj.dtype)
        return {"__ndarray__": True, "data": obj.tobytes(), "dtype": obj.dtype.str, "shape": list(obj.shape)}
    if isinstance(obj, np.bool_ | np.integer | np.floating):
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not serializable")


def _vla_png_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray) and obj.ndim == 3 and obj.dtype == np.uint8 and obj.shape[2] in (3, 4):
        from PIL import Image  # noqa: PLC0415

        out = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(obj)).save(out, format="PNG")
        return {"__image__": True, "format": "png", "data": out.getvalue(), "shape": list(obj.shape)}
    return _vla_default(obj)


# --- decoding -----------------------------------------------------------------------------------


def unpackb(
    data: bytes | bytearray | memoryview, *, dialect: Dialect = "openpi", limits: Limits = DEFAULT_LIMITS
) -> Any:
    """The object one message holds, arrays decoded (read-only views of the message where raw).

    Raises:
        WireFormatError: Anything malformed or refused, naming what.
    """
    return decode_tree(unpack_tree(data, limits=limits), dialect=dialect, limits=limits)


def unpack_tree(data: bytes | bytearray | memoryview, *, limits: Limits = DEFAULT_LIMITS) -> Any:
    """The message's msgpack tree, bounded and checked; arrays stay in their encoded form.

    Raises:
        WireFormatError: Too large, too deep, too many entries, not msgpack, or a value that is not a
            map, list, text, bytes, number, boolean or nil.
    """
    if len(data) > limits.max_bytes:
        raise WireFormatError(f"a message of {len(data)} bytes exceeds the limit of {limits.max_bytes}")
    try:
        tree = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            max_array_len=limits.max_entries,
            max_map_len=limits.max_entries,
            max_ext_len=0,
            ext_hook=_refuse_ext,
        )
    except (ValueError, msgpack.UnpackException) as exc:
        raise WireFormatError(f"not a msgpack message: {_brief(exc)}") from None
    _check_tree(tree, limits)
    return tree


def _refuse_ext(code: int, _data: bytes) -> Any:
    raise WireFormatError(f"msgpack extension type {code} is refused")


def _check_tree(tree: Any, limits: Limits) -> None:
    """Depth, entry count and value types, top down without recursion."""
    entries = 0
    stack: list[tuple[Any, int]] = [(tree, 1)]
    while stack:
        node, depth = stack.pop()
        if isinstance(node, dict | list):
            if depth > limits.max_depth:
                raise WireFormatError(f"message nested deeper than {limits.max_depth}")
            entries += len(node)
            if entries > limits.max_entries:
                raise WireFormatError(f"message holds more than {limits.max_entries} entries")
            stack.extend((child, depth + 1) for child in (node.values() if isinstance(node, dict) else node))
        elif not isinstance(node, str | bytes | int | float | bool) and node is not None:
            raise WireFormatError(f"msgpack value of type {type(node).__name__} is refused")


def decode_tree(tree: Any, *, dialect: Dialect = "openpi", limits: Limits = DEFAULT_LIMITS) -> Any:
    """``tree`` (from :func:`unpack_tree`) with its encoded arrays, scalars and images decoded.

    Raises:
        WireFormatError: An encoded array, scalar or image that is malformed or refused.
    """
    if isinstance(tree, list):
        return [decode_tree(item, dialect=dialect, limits=limits) for item in tree]
    if not isinstance(tree, dict):
        return tree
    header = array_header(tree, dialect=dialect, limits=limits)
    if header is not None:
        return _decode_array(tree, header, dialect, limits)
    if dialect == "openpi" and b"__npgeneric__" in tree:
        return _decode_scalar(tree)
    return {key: decode_tree(value, dialect=dialect, limits=limits) for key, value in tree.items()}


def array_header(node: Any, *, dialect: Dialect = "openpi", limits: Limits = DEFAULT_LIMITS) -> ArrayHeader | None:
    """The checked header of an encoded array (or vla-eval image), ``None`` when ``node`` is none.

    Raises:
        WireFormatError: It is marked as an array but its shape, dtype or size is malformed or refused.
    """
    if not isinstance(node, dict):
        return None
    keys = _KEYS[dialect]
    if keys.ndarray in node:
        dtype = _dtype(node.get(keys.dtype))
        shape = _shape(node.get(keys.shape), limits)
        data = node.get(keys.data)
        if not isinstance(data, bytes):
            raise WireFormatError("array data is not bytes")
        if math.prod(shape) * dtype.itemsize != len(data):
            raise WireFormatError(f"array of {len(data)} bytes announced as shape {_brief(shape)} of {dtype.str}")
        return ArrayHeader(shape, dtype)
    if dialect == "vla_eval" and "__image__" in node:
        fmt = node.get("format")
        if fmt == "raw":
            return array_header({**node, "__ndarray__": True}, dialect=dialect, limits=limits)
        if fmt not in _IMAGE_FORMATS:
            raise WireFormatError(f"image format {_brief(fmt)} is refused (png, jpeg, raw)")
        shape = _shape(node.get("shape"), limits)
        if len(shape) != 3 or shape[2] not in _IMAGE_MODES.values():
            raise WireFormatError(f"an image is (H, W, 1|3|4), not {_brief(shape)}")
        if not isinstance(node.get("data"), bytes):
            raise WireFormatError("image data is not bytes")
        return ArrayHeader(shape, np.dtype(np.uint8), image_format=fmt)
    return None


@dataclass(frozen=True)
class _Keys:
    ndarray: Any
    data: Any
    dtype: Any
    shape: Any


_KEYS: Final[dict[str, _Keys]] = {
    "openpi": _Keys(b"__ndarray__", b"data", b"dtype", b"shape"),
    "vla_eval": _Keys("__ndarray__", "data", "dtype", "shape"),
}


def _dtype(value: Any) -> np.dtype[Any]:
    if not isinstance(value, str) or not _DTYPE_RE.fullmatch(value):
        raise WireFormatError(f"dtype {_brief(value)} is refused (numbers and booleans only)")
    return np.dtype(value)


def _shape(value: Any, limits: Limits) -> tuple[int, ...]:
    if (
        not isinstance(value, list)
        or len(value) > limits.max_dims
        or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in value)
    ):
        raise WireFormatError(f"bad shape {_brief(value)} (at most {limits.max_dims} non-negative integers)")
    if math.prod(d for d in value if d) > limits.max_elements:
        raise WireFormatError(f"shape {_brief(value)} has more than {limits.max_elements} elements")
    return tuple(value)


def _decode_array(node: dict[Any, Any], header: ArrayHeader, dialect: Dialect, limits: Limits) -> np.ndarray:
    if header.image_format is not None:
        return _decode_image(node["data"], header)
    return np.ndarray(buffer=node[_KEYS[dialect].data], dtype=header.dtype, shape=header.shape)


def _decode_scalar(node: dict[Any, Any]) -> Any:
    dtype = _dtype(node.get(b"dtype"))
    value = node.get(b"data")
    if not isinstance(value, int | float) or (isinstance(value, float) and dtype.kind in "biu"):
        raise WireFormatError(f"numpy scalar of {dtype.str} holds {_brief(value)}")
    try:
        return dtype.type(value)
    except (OverflowError, ValueError) as exc:
        raise WireFormatError(f"numpy scalar of {dtype.str} holds {_brief(value)}: {exc}") from None


def _decode_image(data: bytes, header: ArrayHeader) -> np.ndarray:
    from PIL import Image  # noqa: PLC0415

    assert header.image_format is not None
    height, width, channels = header.shape
    try:
        with Image.open(io.BytesIO(data), formats=[_IMAGE_FORMATS[header.image_format]]) as image:
            # The header's size and mode are known before any pixel is decoded: refuse a mismatch first.
            if image.size != (width, height) or _IMAGE_MODES.get(image.mode) != channels:
                raise WireFormatError(
                    f"{header.image_format} image of {image.size[::-1]} {image.mode} announced as {list(header.shape)}"
                )
            pixels = np.asarray(image)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise WireFormatError(f"undecodable {header.image_format} image ({_brief(exc)})") from None
    return pixels.reshape(header.shape)


def _brief(value: Any) -> str:
    """``repr(value)`` (or an exception's text) cut short: errors quote hostile input, so they bound it."""
    text = str(value) if isinstance(value, BaseException) else repr(value)
    text = text.replace("\n", " ")
    return text if len(text) <= 80 else f"{text[:77]}..."
