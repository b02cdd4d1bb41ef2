"""What the console shows, handed over by the tick and thumbnail threads and read by the server.

The producers only store references (O(1), no copies, no locks on the tick thread): the newest
tick with its world state, the newest thumbnail of each camera, the episode under way. The
server reads them on its own thread, at its own rate, and renders the page's messages from them:
older values nobody read are simply replaced (newest wins, per key).

Messages to the page are JSON text (``type`` says which) and binary camera frames:
``uint32`` big-endian length of a JSON header (``sensor_id``, ``stamp_ns``, ``width``,
``height``), the header, then the JPEG bytes.
"""

from __future__ import annotations

import json
import math
import re
import struct
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from openral_core import ROSConfigError, TickResult, WorldState
from openral_observability.observer import Thumbnail

CONTROL_LABELS: Mapping[str, str] = {
    "stop": "Stop",
    "next": "Next episode",
    "rerecord": "Re-record",
    "takeover": "Takeover",
    "highlight": "Highlight",
}
"""Button labels of the controls commands register (any other name shows as itself)."""

_CONTROL_NAME = re.compile(r"^[a-z][a-z0-9_]{0,31}$")
_HEADER = struct.Struct(">I")


@dataclass(frozen=True)
class Control:
    """A button on the page: ``action`` runs (off the server's event loop) when it is pressed."""

    name: str
    label: str
    action: Callable[[], object]


class Controls:
    """The controls a command registered, in registration order; safe to change while pages are open."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._controls: dict[str, Control] = {}

    def register(self, name: str, action: Callable[[], object], *, label: str | None = None) -> None:
        """Show a button ``name`` that runs ``action``; registering a name again replaces its action.

        Raises:
            ROSConfigError: ``name`` is not a short lower-case identifier.
        """
        if not _CONTROL_NAME.match(name):
            raise ROSConfigError(f"a console control is a short lower-case identifier, got {name!r}", field="control")
        control = Control(name, label or CONTROL_LABELS.get(name, name), action)
        with self._lock:
            self._controls[name] = control

    def get(self, name: str) -> Control | None:
        """The control called ``name``, ``None`` when none is registered."""
        with self._lock:
            return self._controls.get(name)

    def names(self) -> list[str]:
        """Registered names, in order."""
        with self._lock:
            return list(self._controls)

    def describe(self) -> list[dict[str, str]]:
        """``[{"name", "label"}]`` in order: the buttons the page shows."""
        with self._lock:
            return [{"name": c.name, "label": c.label} for c in self._controls.values()]


class ConsoleFeed:
    """The newest of everything the page shows, written by the producers, read by the server.

    Args:
        clock: Seconds clock for the samples' times (the page's plot axis).
    """

    def __init__(self, *, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._t0 = clock()
        self._latest: tuple[TickResult, WorldState | None] | None = None
        self.ticks_seen = 0
        """Ticks handed over since the console was built (rises across runs and episodes)."""
        self._thumbs: dict[str, Thumbnail] = {}
        self.episode: tuple[int, str] | None = None
        """The episode under way (index, task), ``None`` between episodes."""
        self.status: Callable[[], Mapping[str, Any]] | None = None
        """The runner's health, as :func:`openral_console.status.runner_status` builds it; set by the command."""
        self.controls = Controls()

    # -- producers (tick thread, thumbnail worker): reference stores only ------------------

    def put_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Make ``tick`` the newest (tick thread; O(1))."""
        self._latest = (tick, world)
        self.ticks_seen += 1

    def put_thumbnail(self, thumb: Thumbnail) -> None:
        """Make ``thumb`` its camera's newest (thumbnail worker; O(1))."""
        self._thumbs[thumb.sensor_id] = thumb

    # -- the server's side -----------------------------------------------------------------

    def thumbnails(self) -> dict[str, Thumbnail]:
        """The newest thumbnail of each camera (a copy of the mapping; the thumbnails are shared)."""
        return dict(self._thumbs)

    def sample(self) -> dict[str, Any] | None:
        """The newest tick as one plot sample: measured joints, the commanded action (row 0 sent), the tick index."""
        latest = self._latest
        if latest is None:
            return None
        tick, world = latest
        joints = None if world is None else world.joint_state
        return {
            "t": round(self._clock() - self._t0, 4),
            "tick_idx": tick.tick_idx,
            "names": [] if joints is None else list(joints.names),
            "measured": None if joints is None else [float(p) for p in joints.positions],
            "commanded": None if tick.sent_action is None else list(tick.sent_action),
            "applied": tick.action_applied,
        }

    def state(self, status: Mapping[str, Any] | None) -> dict[str, Any]:
        """The ``state`` message: counters, the newest sample, the health, the episode, the buttons, the cameras."""
        episode = self.episode
        return {
            "type": "state",
            "ticks": self.ticks_seen,
            "sample": self.sample(),
            "status": None if status is None else dict(status),
            "episode": None if episode is None else {"index": episode[0], "task": episode[1]},
            "controls": self.controls.describe(),
            "cameras": sorted(self._thumbs),
        }


def dumps(message: Mapping[str, Any]) -> str:
    """Compact JSON; NaN and infinities (not JSON) become ``null``, anything else unknown its ``str``."""
    try:
        return json.dumps(message, allow_nan=False, separators=(",", ":"), default=str)
    except ValueError:
        return json.dumps(_finite(message), allow_nan=False, separators=(",", ":"), default=str)


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {str(key): _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value


def pack_thumbnail(thumb: Thumbnail) -> bytes:
    """One binary camera frame for the page: header length, JSON header, JPEG."""
    header = json.dumps(
        {"sensor_id": thumb.sensor_id, "stamp_ns": thumb.stamp_ns, "width": thumb.width, "height": thumb.height},
        separators=(",", ":"),
    ).encode()
    return _HEADER.pack(len(header)) + header + thumb.jpeg


def unpack_thumbnail(data: bytes) -> tuple[dict[str, Any], bytes]:
    """The header and JPEG of a frame :func:`pack_thumbnail` made (for tests and other readers).

    Raises:
        ValueError: Not such a frame.
    """
    if len(data) < _HEADER.size:
        raise ValueError("too short for a camera frame")
    (size,) = _HEADER.unpack_from(data)
    end = _HEADER.size + size
    if end > len(data):
        raise ValueError("camera frame header runs past its end")
    header = json.loads(data[_HEADER.size : end])
    if not isinstance(header, dict):
        raise ValueError("camera frame header is not an object")
    return header, data[end:]
