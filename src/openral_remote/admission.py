"""What a policy server takes in: requests checked from their header alone, before a byte of them is decoded.

A request is one message (:mod:`openral_remote.codec`); its header says every field's kind and
shape. That is enough to refuse, in microseconds and on Zenoh's own thread, what would cost the
worker dearly: a message over the size limit, an image of a camera the policy does not read, or
one larger than the limit in pixels (a small JPEG can announce a huge picture; decoding it is
what starves the robots and leaves the memory behind). Images that pass are checked again when
decoded (the JPEG's own size must be the announced one).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from openral_remote.codec import WireFormatError, read_header

IMAGE_FIELD = "image."
META_SUFFIX = ".meta"


class ServeLimits(BaseModel):
    """How much a policy server takes: per request, per client, and at once."""

    model_config = ConfigDict(frozen=True, extra="forbid")

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


def admit(message: bytes, *, limits: ServeLimits, images: ImagesRead) -> None:
    """Refuse ``message`` unless its size and every image it announces are within what the server takes.

    Raises:
        Refused: Naming the field and the limit.
        WireFormatError: The header is malformed.
    """
    if len(message) > limits.max_request_bytes:
        raise Refused(f"a request of {len(message)} bytes is over the server's {limits.max_request_bytes}")
    for name, entry in read_header(message).items():
        if not name.startswith(IMAGE_FIELD):
            continue
        sensor = name.removeprefix(IMAGE_FIELD).removesuffix(META_SUFFIX)
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


__all__ = ["ImagesRead", "Refused", "ServeLimits", "admit"]
