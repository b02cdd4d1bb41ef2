"""What a policy server takes in: requests checked from their header alone, before a byte of them is decoded.

A request is one message (:mod:`openral_remote.codec`); its header says every field's kind and
shape. That is enough to refuse, in microseconds and on Zenoh's own thread, what would cost the
worker dearly: a message over the size limit, an image of a camera the policy does not read, or
one larger than the limit in pixels (a small JPEG can announce a huge picture; decoding it is
what starves the robots and leaves the memory behind). Images that pass are checked again when
decoded (the JPEG's own size must be the announced one).

What a chunk request carries besides the observation is bounded by the policy
(:class:`RequestBounds`, from its meta): no more earlier observations than it reads (each checked
as the current one is), a prefix no longer than its chunk and as wide as its action, and integers
(tick, delay, seed) that fit 64 bits.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from openral_remote.codec import WireFormatError, read_header
from openral_remote.observation import HISTORY, INFERENCE_DELAY, OBS_TICK, PREFIX, SEED

IMAGE_FIELD = "image."
META_SUFFIX = ".meta"
_INT_RANGES: dict[str, tuple[int, int]] = {
    OBS_TICK: (-(1 << 63), 1 << 63),
    INFERENCE_DELAY: (0, 1 << 31),
    SEED: (-(1 << 63), 1 << 64),
}
"""Integer fields and their bounds (low inclusive, high exclusive)."""
_PREFIX_DTYPES = frozenset({"float32", "float64"})


class ServeLimits(BaseModel):
    """How much a policy server takes: per request, per client, and at once."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    max_batch: int = Field(default=1, ge=1, le=1024, description="Requests one inference takes (1: no batching).")
    max_wait_ms: float = Field(
        default=2.0, ge=0, le=1000, description="How long a request may wait for a batch to fill (never longer)."
    )
    max_clients: int = Field(
        default=32, ge=1, le=4096, description="Robots with an episode on the server at once (each may hold a model)."
    )
    client_idle_s: float = Field(
        default=30.0, gt=0, description="A client silent this long gives its episode up to a new one when full."
    )
    max_pending: int = Field(default=64, ge=1, le=65_536, description="Requests waiting at once, all clients.")
    max_request_bytes: int = Field(default=64 << 20, ge=1024, description="The largest request taken, bytes.")
    max_image_pixels: int = Field(
        default=2560 * 1600, ge=1, description="The largest image taken (width x height), raw or compressed."
    )


class Refused(WireFormatError):
    """A request the server will not take (the reply names why)."""


@dataclass(frozen=True)
class ImagesRead:
    """The cameras a policy reads, from its ``observation`` (empty: it does not say, so any)."""

    every: bool
    sensors: frozenset[str]

    @classmethod
    def of(cls, observation: Sequence[str]) -> ImagesRead:
        fields = set(observation)
        every = not fields or "images" in fields
        return cls(every, frozenset(name.removeprefix("images.") for name in fields if name.startswith("images.")))

    def reads(self, sensor: str) -> bool:
        return self.every or sensor in self.sensors


@dataclass(frozen=True)
class RequestBounds:
    """What one request may carry besides its observation (a policy's meta says).

    Attributes:
        history: Earlier observations at most (the policy's observation steps less one).
        prefix_rows: Prefix rows at most (its chunk size).
        action_dims: The prefix's width.
    """

    history: int = 0
    prefix_rows: int = 0
    action_dims: int = 0


def admit(message: bytes, *, limits: ServeLimits, images: ImagesRead, bounds: RequestBounds | None = None) -> None:
    """Refuse ``message`` unless its size, every image it announces and its other fields are within bounds.

    Raises:
        Refused: Naming the field and the limit.
        WireFormatError: The header is malformed.
    """
    if len(message) > limits.max_request_bytes:
        raise Refused(f"a request of {len(message)} bytes is over the server's {limits.max_request_bytes}")
    bounds = bounds or RequestBounds()
    for name, entry in read_header(message).items():
        field = _past_field(name, bounds) if name.startswith(HISTORY) else name
        if field in _INT_RANGES and field == name:
            _check_int(name, entry, *_INT_RANGES[field])
        elif name == PREFIX:
            _check_prefix(entry, bounds)
        if not field.startswith(IMAGE_FIELD):
            continue
        sensor = field.removeprefix(IMAGE_FIELD).removesuffix(META_SUFFIX)
        if not images.reads(sensor):
            raise Refused(f"field {name!r}: the policy reads no camera {sensor!r}")
        if name.endswith(META_SUFFIX):
            _check_pixels(name, _announced_size(name, entry), limits)
        elif isinstance(entry, dict) and entry.get("kind") == "jpeg":
            _check_pixels(name, _image_size(name, entry.get("shape")), limits)
        elif isinstance(entry, dict) and entry.get("kind") == "array":
            shape = entry.get("shape")
            if isinstance(shape, list) and len(shape) >= 2:  # raw pixels; a compressed frame's bytes are 1-D
                _check_pixels(name, _image_size(name, shape), limits)


def check_seed(value: Any) -> int | None:
    """A seed as a robot sent it (``None``, or an integer within 64 bits).

    Raises:
        Refused: Anything else.
    """
    if value is None:
        return None
    low, high = _INT_RANGES[SEED]
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value < high:
        raise Refused(f"field {SEED!r}: not an integer within 64 bits")
    return value


def _past_field(name: str, bounds: RequestBounds) -> str:
    """The field of an earlier observation, its index checked against the policy's history."""
    index, dot, field = name.removeprefix(HISTORY).partition(".")
    if not (dot and index.isdecimal() and len(index) <= 2 and index == str(int(index)) and int(index) < bounds.history):
        raise Refused(f"field {name[:60]!r}: the policy reads {bounds.history} earlier observations")
    return field


def _check_int(name: str, entry: Any, low: int, high: int) -> None:
    value = entry.get("value") if isinstance(entry, dict) and entry.get("kind") == "value" else None
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value < high:
        raise Refused(f"field {name!r}: not an integer in [{low}, {high})")


def _check_prefix(entry: Any, bounds: RequestBounds) -> None:
    shape = entry.get("shape") if isinstance(entry, dict) and entry.get("kind") == "array" else None
    if not isinstance(shape, list) or len(shape) != 2 or entry.get("dtype") not in _PREFIX_DTYPES:
        raise Refused(f"field {PREFIX!r}: not float rows")
    rows, dims = shape
    if not isinstance(rows, int) or rows > bounds.prefix_rows or dims != bounds.action_dims:
        raise Refused(
            f"field {PREFIX!r}: {str(shape)[:40]} rows, the policy takes at most "
            f"({bounds.prefix_rows}, {bounds.action_dims})"
        )


def _image_size(name: str, shape: Any) -> tuple[int, int]:
    if not isinstance(shape, list) or len(shape) not in (2, 3) or not all(isinstance(d, int) for d in shape):
        raise Refused(f"field {name!r}: an image is (H, W) or (H, W, C), not {str(shape)[:40]}")
    if len(shape) == 3 and shape[2] not in (1, 3, 4):
        raise Refused(f"field {name!r}: {shape[2]} channels (1, 3 or 4)")
    return int(shape[0]), int(shape[1])


def _announced_size(name: str, entry: Any) -> tuple[int, int]:
    value = entry.get("value") if isinstance(entry, dict) else None
    if not isinstance(value, dict):
        raise Refused(f"field {name!r}: not an image description")
    height, width = value.get("height"), value.get("width")
    if not isinstance(height, int) or not isinstance(width, int) or height < 0 or width < 0:
        raise Refused(f"field {name!r}: no width and height")
    return height, width


def _check_pixels(name: str, size: tuple[int, int], limits: ServeLimits) -> None:
    pixels = math.prod(size)
    if pixels > limits.max_image_pixels:
        raise Refused(
            f"field {name!r}: an image of {size[1]}x{size[0]} is over the server's {limits.max_image_pixels} pixels"
        )


__all__ = ["ImagesRead", "Refused", "RequestBounds", "ServeLimits", "admit", "check_seed"]
