"""``FoxgloveSink``: every tick to a live Foxglove WebSocket, off the tick thread.

Channels (one schema each; JSON messages carry a JSON Schema, so Foxglove plots any field):

- ``/openral/tick`` (JSON ``openral.Tick``): one message per tick with the phase timings
  (``tick_ms``, ``sensors_ms``, ``world_state_ms``, ``inference_ms``, ``safety_ms``, ``hal_ms``),
  ``lateness_ms``, ``deadline_missed``, ``action_applied``, ``withheld_reason``,
  ``requested_action`` / ``sent_action``, ``stale_sensors``, ``safety_violations``, and the
  sink's own ``dropped`` count.
- ``/joint_states`` (JSON ``openral.JointState``): one message per tick that saw a joint state,
  with ``name``, ``position``, ``velocity``, ``effort`` (ROS ``sensor_msgs/JointState`` field names).
- ``/openral/safety`` (JSON ``openral.SafetyEvent``): one message per safety violation
  (``kind="safety_violation"``) and one per withheld action (``kind="action_withheld"``), with
  ``reason``.
- ``/camera/<sensor_id>/compressed`` (``foxglove.CompressedImage``): the runner's JPEG thumbnails
  of each camera (at its ``thumbnail_hz``; encoded once for every viewer, see
  :mod:`openral_runner.thumbnails`).

Times: a message's log time is the wall-clock time at which its tick was handed to the sink,
taken as ``time.monotonic_ns()`` plus one offset to ``time.time_ns()`` sampled when the sink is
built. Every stamp therefore keeps exact monotonic intervals (no NTP steps inside a recording).
``timestamp`` fields inside messages are the tick's hand-over time for ticks and safety events,
and the measurement's own monotonic stamp (joint-state read, frame capture) mapped with the same
offset for joint states and images.

The tick thread only appends a reference to a bounded queue (the oldest entry is dropped and
counted when it is full); thumbnails arrive from the runner's thumbnail worker into a
latest-per-camera slot. A worker thread wakes every ``flush_interval_s`` and serialises and logs
what accumulated.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import (
    JointState,
    ROSConfigError,
    ROSDependencyMissing,
    TickResult,
    WorldState,
)
from openral_core.config import validate_model
from openral_observability.observer import Thumbnail, TickObserver

try:
    import foxglove
    from foxglove.channels import CompressedImageChannel
    from foxglove.messages import CompressedImage, Timestamp
    from foxglove.websocket import WebSocketServer
except ImportError as exc:  # pragma: no cover - exercised with the extra missing
    raise ROSDependencyMissing("foxglove", extra="foxglove", needed_for="the Foxglove live view") from exc

_log = structlog.get_logger(__name__)

TOPIC_TICK = "/openral/tick"
TOPIC_JOINT_STATES = "/joint_states"
TOPIC_SAFETY = "/openral/safety"
TOPIC_CAMERA = "/camera/{sensor_id}/compressed"

SAFETY_KIND_VIOLATION = "safety_violation"
SAFETY_KIND_WITHHELD = "action_withheld"

DEFAULT_PORT = 8765
"""Foxglove's usual WebSocket port: what ``--foxglove`` without a value serves on."""

_TIME: dict[str, Any] = {
    "type": "object",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
}
_NUMBERS: dict[str, Any] = {"type": ["array", "null"], "items": {"type": ["number", "null"]}}
_STRINGS: dict[str, Any] = {"type": "array", "items": {"type": "string"}}

TICK_SCHEMA: dict[str, Any] = {
    "title": "openral.Tick",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "tick_idx": {"type": "integer"},
        "tick_ms": {"type": "number"},
        "sensors_ms": {"type": "number"},
        "world_state_ms": {"type": "number"},
        "inference_ms": {"type": "number"},
        "safety_ms": {"type": "number"},
        "hal_ms": {"type": "number"},
        "lateness_ms": {"type": "number"},
        "deadline_missed": {"type": "boolean"},
        "action_applied": {"type": "boolean"},
        "withheld_reason": {"type": ["string", "null"]},
        "requested_action": _NUMBERS,
        "sent_action": _NUMBERS,
        "stale_sensors": _STRINGS,
        "safety_violations": _STRINGS,
        "dropped": {"type": "integer", "description": "ticks this sink dropped so far (queue full)"},
    },
}
JOINT_STATE_SCHEMA: dict[str, Any] = {
    "title": "openral.JointState",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "tick_idx": {"type": "integer"},
        "name": _STRINGS,
        "position": _NUMBERS,
        "velocity": _NUMBERS,
        "effort": _NUMBERS,
    },
}
SAFETY_SCHEMA: dict[str, Any] = {
    "title": "openral.SafetyEvent",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "tick_idx": {"type": "integer"},
        "kind": {"type": "string", "enum": [SAFETY_KIND_VIOLATION, SAFETY_KIND_WITHHELD]},
        "reason": {"type": "string"},
        "action_applied": {"type": "boolean"},
        "requested_action": _NUMBERS,
        "sent_action": _NUMBERS,
    },
}


_Item = tuple[TickResult, JointState | None, int]


class FoxgloveParams(BaseModel):
    """Parameters of the ``foxglove`` observer in a deployment's ``observers:`` block."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    port: int = Field(default=8765, ge=0, le=65535, description="Serve the live WebSocket here (0: any free port).")
    host: str = Field(default="127.0.0.1", description="Interface the live server binds to.")


class FoxgloveSink(TickObserver):
    """A tick observer that serves a live Foxglove WebSocket.

    A file of the session is the ROS 2 bag (:mod:`openral_dataset.ros2_bag`, ``--mcap``). The
    channels here log into :attr:`context`; a caller can attach more Foxglove sinks to it.

    Args:
        port: Serve a Foxglove WebSocket on this port (0 picks a free one; see :attr:`port`).
            ``None`` serves nothing (the channels only reach sinks attached to :attr:`context`).
            The port is bound by :meth:`start` (the runner calls it at activation), never here.
        host: Interface the server binds to.
        queue_size: Ticks buffered for the worker; when full the oldest is dropped and counted.
        flush_interval_s: How often the worker wakes to publish what was handed over (the live
            view's added latency). The tick thread wakes it early only when the queue is half
            full: waking a sleeping thread costs the tick thread tens of µs, appending costs ~1 µs.
        close_timeout_s: How long :meth:`close` waits for the worker to drain.

    Raises:
        ROSConfigError: ``queue_size`` is below 1.
    """

    def __init__(
        self,
        *,
        port: int | None = None,
        host: str = "127.0.0.1",
        queue_size: int = 256,
        flush_interval_s: float = 0.02,
        close_timeout_s: float = 5.0,
    ) -> None:
        if queue_size < 1:
            raise ROSConfigError(f"queue_size must be at least 1, got {queue_size}", field="queue_size")
        self._close_timeout_s = close_timeout_s
        self._flush_interval_s = flush_interval_s
        self._wake_at = max(1, queue_size // 2)
        self._offset_ns = time.time_ns() - time.monotonic_ns()
        self._context = foxglove.Context()
        self._listen = None if port is None else (host, port)
        self._server: WebSocketServer | None = None

        self._tick_channel = foxglove.Channel(TOPIC_TICK, schema=TICK_SCHEMA, context=self._context)
        self._joint_channel = foxglove.Channel(TOPIC_JOINT_STATES, schema=JOINT_STATE_SCHEMA, context=self._context)
        self._safety_channel = foxglove.Channel(TOPIC_SAFETY, schema=SAFETY_SCHEMA, context=self._context)
        self._camera_channels: dict[str, CompressedImageChannel] = {}

        self._cond = threading.Condition()
        self._ticks: deque[_Item] = deque(maxlen=queue_size)
        self._images: dict[str, tuple[Thumbnail, int]] = {}
        self._closed = False
        self.dropped = 0
        self.images_replaced = 0
        self.ticks_published = 0
        self.images_published = 0
        self.publish_errors = 0
        self._thread = threading.Thread(target=self._run, name="openral-foxglove", daemon=True)
        self._thread.start()

    def start(self) -> None:
        """Bind the live server (when a port was given). Idempotent; building the sink binds nothing.

        Raises:
            ROSConfigError: The port cannot be bound.
        """
        if self._listen is None or self._server is not None:
            return
        host, port = self._listen
        try:
            self._server = foxglove.start_server(name="openral", host=host, port=port, context=self._context)
        except RuntimeError as exc:
            raise ROSConfigError(
                f"cannot serve Foxglove on {host}:{port}: {exc}", hint="choose another port: --foxglove PORT"
            ) from exc

    @classmethod
    def from_config(
        cls, params: Mapping[str, Any], *, robot: Any, env: Any, base_dir: Path | None = None
    ) -> FoxgloveSink:
        """Plugin constructor (observer ``foxglove``); ``params`` are validated as :class:`FoxgloveParams`.

        Images come from the runner's thumbnails: give the deployment a ``thumbnail_hz``.

        Raises:
            ROSConfigError: A wrong parameter (named with the allowed keys).
        """
        config = validate_model(FoxgloveParams, dict(params), field_prefix="observers[].params")
        return cls(port=config.port, host=config.host)

    @property
    def context(self) -> foxglove.Context:
        """The Foxglove context the channels log into (attach more sinks to it)."""
        return self._context

    # -- what the CLI reads ---------------------------------------------------------------

    @property
    def port(self) -> int | None:
        """The port the live server listens on (the real one when 0 was asked), ``None`` without a server."""
        return None if self._server is None else self._server.port

    @property
    def app_url(self) -> str | None:
        """A Foxglove app link that opens this live server, ``None`` without a server."""
        return None if self._server is None else self._server.app_url()

    # -- TickObserver ---------------------------------------------------------------------

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Hand one tick over to the worker (tick thread; never blocks on I/O, touches no pixels)."""
        now_ns = time.monotonic_ns()
        joints = None if world is None else world.joint_state
        with self._cond:
            if self._closed:
                return
            if len(self._ticks) == self._ticks.maxlen:
                self.dropped += 1
            self._ticks.append((tick, joints, now_ns))
            if len(self._ticks) == self._wake_at:
                self._cond.notify()

    def on_thumbnail(self, thumb: Thumbnail) -> None:
        """Keep a camera's newest thumbnail for the worker (called on the runner's thumbnail thread)."""
        now_ns = time.monotonic_ns()
        with self._cond:
            if self._closed:
                return
            if thumb.sensor_id in self._images:
                self.images_replaced += 1
            self._images[thumb.sensor_id] = (thumb, now_ns)

    def close(self) -> None:
        """Drain what was handed over, finish the MCAP file and stop the server. Idempotent."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self._thread.join(self._close_timeout_s)
        if self._thread.is_alive():
            _log.warning("foxglove sink did not drain in time; closing anyway", timeout_s=self._close_timeout_s)
        with ExitStack() as stack:
            # Unwinds in reverse: channels, then the server.
            if self._server is not None:
                stack.callback(self._server.stop)
            for channel in (self._tick_channel, self._joint_channel, self._safety_channel):
                stack.callback(channel.close)
            for camera in list(self._camera_channels.values()):
                stack.callback(camera.close)
        if self.dropped or self.publish_errors:
            _log.warning("foxglove sink lost ticks", dropped=self.dropped, publish_errors=self.publish_errors)

    def __enter__(self) -> FoxgloveSink:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # -- worker -------------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._closed:
                    self._cond.wait(self._flush_interval_s)
                ticks = list(self._ticks)
                self._ticks.clear()
                images, self._images = self._images, {}
                if self._closed and not ticks and not images:
                    return
            for item in ticks:
                self._guarded(self._publish_tick, item)
            for thumb, handed_ns in images.values():
                self._guarded(self._publish_image, thumb, handed_ns)

    def _guarded(self, publish: Callable[..., None], *args: Any) -> None:
        try:
            publish(*args)
        except Exception as exc:  # the worker must outlive one bad message
            self.publish_errors += 1
            if self.publish_errors == 1:
                _log.error("foxglove sink failed to publish; counting further failures", error=repr(exc))

    def _publish_tick(self, item: _Item) -> None:
        tick, joints, handed_ns = item
        log_time = handed_ns + self._offset_ns
        stamp = _stamp(log_time)
        self._tick_channel.log(
            _dumps(
                {
                    "timestamp": stamp,
                    "tick_idx": tick.tick_idx,
                    "tick_ms": tick.tick_ms,
                    "sensors_ms": tick.sensors_ms,
                    "world_state_ms": tick.world_state_ms,
                    "inference_ms": tick.inference_ms,
                    "safety_ms": tick.safety_ms,
                    "hal_ms": tick.hal_ms,
                    "lateness_ms": tick.lateness_ms,
                    "deadline_missed": tick.deadline_missed,
                    "action_applied": tick.action_applied,
                    "withheld_reason": tick.withheld_reason,
                    "requested_action": tick.requested_action,
                    "sent_action": tick.sent_action,
                    "stale_sensors": tick.stale_sensors,
                    "safety_violations": tick.safety_violations,
                    "dropped": self.dropped,
                }
            ),
            log_time=log_time,
        )
        if joints is not None:
            measured = joints.stamp_ns + self._offset_ns if joints.stamp_ns else log_time
            self._joint_channel.log(
                _dumps(
                    {
                        "timestamp": _stamp(measured),
                        "tick_idx": tick.tick_idx,
                        "name": joints.names,
                        "position": joints.positions,
                        "velocity": joints.velocities,
                        "effort": joints.efforts,
                    }
                ),
                log_time=log_time,
            )
        events = [(SAFETY_KIND_VIOLATION, reason) for reason in tick.safety_violations]
        if tick.withheld_reason is not None:
            events.append((SAFETY_KIND_WITHHELD, tick.withheld_reason))
        for kind, reason in events:
            self._safety_channel.log(
                _dumps(
                    {
                        "timestamp": stamp,
                        "tick_idx": tick.tick_idx,
                        "kind": kind,
                        "reason": reason,
                        "action_applied": tick.action_applied,
                        "requested_action": tick.requested_action,
                        "sent_action": tick.sent_action,
                    }
                ),
                log_time=log_time,
            )
        self.ticks_published += 1

    def _publish_image(self, thumb: Thumbnail, handed_ns: int) -> None:
        channel = self._camera_channels.get(thumb.sensor_id)
        if channel is None:
            topic = TOPIC_CAMERA.format(sensor_id=thumb.sensor_id)
            channel = self._camera_channels[thumb.sensor_id] = CompressedImageChannel(topic, context=self._context)
        channel.log(
            CompressedImage(
                timestamp=_timestamp(thumb.stamp_ns + self._offset_ns),
                frame_id=thumb.frame_id or thumb.sensor_id,
                data=thumb.jpeg,
                format="jpeg",
            ),
            log_time=handed_ns + self._offset_ns,
        )
        self.images_published += 1


def _stamp(wall_ns: int) -> dict[str, int]:
    sec, nsec = divmod(wall_ns, 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def _timestamp(wall_ns: int) -> Timestamp:
    sec, nsec = divmod(wall_ns, 1_000_000_000)
    return Timestamp(sec, nsec)


def _dumps(message: dict[str, Any]) -> bytes:
    """Compact JSON; NaN and infinities (not JSON) become ``null``."""
    try:
        return json.dumps(message, allow_nan=False, separators=(",", ":")).encode()
    except ValueError:
        return json.dumps(_finite(message), allow_nan=False, separators=(",", ":")).encode()


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value
