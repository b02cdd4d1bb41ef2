"""``FoxgloveSink``: every tick to a live Foxglove WebSocket, off the tick thread.

Channels (one schema each; JSON messages carry a JSON Schema, so Foxglove plots any field;
non-finite numbers are sent as ``null``):

- ``/openral/tick`` (JSON ``openral.Tick``): one message per tick, its ``TickResult`` as
  ``model_dump(mode="json")`` under the schema ``TickResult.model_json_schema()`` gives, plus
  ``timestamp`` and the sink's ``dropped`` count: a field added to ``TickResult`` appears unedited.
- ``/joint_states`` (JSON ``openral.JointState``): one message per tick that saw a joint state,
  with ``name``, ``position``, ``velocity``, ``effort`` (ROS ``sensor_msgs/JointState`` field names).
- ``/openral/safety`` (JSON ``openral.SafetyEvent``): one message per safety violation
  (``kind="safety_violation"``) and one per withheld action (``kind="action_withheld"``), with ``reason``.
- ``/camera/<sensor_id>/compressed`` (``foxglove.CompressedImage``): the runner's JPEG thumbnails
  (:mod:`openral_runner.thumbnails`, encoded once for every viewer by the ``thumbnails`` observer).

Times: a message's log time is the wall-clock time at which its tick was handed to the sink:
``time.monotonic_ns()`` plus one offset to ``time.time_ns()`` sampled when the sink is built, so
stamps keep exact monotonic intervals (no NTP steps inside a recording). ``timestamp`` fields are
that hand-over time for ticks and safety events, and the measurement's own monotonic stamp
(joint-state read, frame capture) mapped with the same offset for joint states and images.

Ticks go through :class:`~openral_observability.queued_observer.QueuedObserver` (every tick in
order; when the queue is full the oldest is dropped and counted), thumbnails through a
:class:`~openral_observability.latest_observer.LatestPerKeyWorker` (the newest per camera wins;
one still waiting is replaced and counted), each on its own worker.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping
from contextlib import ExitStack
from typing import Any, Final

import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import JointState, ObserverContext, ROSConfigError, ROSDependencyMissing, TickResult, WorldState
from openral_core.config import validate_model
from openral_observability.latest_observer import LatestPerKeyWorker
from openral_observability.observer import Thumbnail
from openral_observability.queued_observer import QueuedObserver

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


def _plain_json_schema(model: type[BaseModel]) -> dict[str, Any]:
    """``model``'s JSON Schema in the plain dialect a viewer reads: no ``$ref``, nullable as a type list.

    Local ``$defs`` references are inlined, and ``anyOf: [X, {"type": "null"}]`` becomes ``X``
    with ``"type": [X's type, "null"]`` (and ``null`` among its ``enum``, if it has one).
    """
    schema = model.model_json_schema(mode="serialization")
    defs = schema.pop("$defs", {})

    def plain(node: Any) -> Any:
        if isinstance(node, list):
            return [plain(item) for item in node]
        if not isinstance(node, dict):
            return node
        if "$ref" in node:
            return plain({**defs[node["$ref"].rsplit("/", 1)[-1]], **{k: v for k, v in node.items() if k != "$ref"}})
        options = node.get("anyOf")
        if isinstance(options, list) and len(options) == 2 and {"type": "null"} in options:
            other = plain(next(option for option in options if option != {"type": "null"}))
            rest = {key: plain(value) for key, value in node.items() if key != "anyOf"}
            if isinstance(other.get("type"), str):
                if "enum" in other:
                    other["enum"] = [*other["enum"], None]
                return {**other, **rest, "type": [other["type"], "null"]}
        return {key: plain(value) for key, value in node.items()}

    out: dict[str, Any] = plain(schema)
    return out


_TIME: Final[dict[str, Any]] = {
    "type": "object",
    "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
}
_NUMBERS: Final[dict[str, Any]] = {"type": ["array", "null"], "items": {"type": ["number", "null"]}}
_STRINGS: Final[dict[str, Any]] = {"type": "array", "items": {"type": "string"}}
_TICK_FIELDS: Final = _plain_json_schema(TickResult)
_SAFETY_TICK_FIELDS: Final = ("tick_idx", "action_applied", "requested_action", "sent_action")
"""The tick's fields a safety event repeats."""

TICK_SCHEMA: dict[str, Any] = {
    **_TICK_FIELDS,
    "title": "openral.Tick",
    "properties": {
        "timestamp": _TIME,
        **_TICK_FIELDS["properties"],
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
        "kind": {"type": "string", "enum": [SAFETY_KIND_VIOLATION, SAFETY_KIND_WITHHELD]},
        "reason": {"type": "string"},
        **{name: _TICK_FIELDS["properties"][name] for name in _SAFETY_TICK_FIELDS},
    },
}


_Item = tuple[TickResult, JointState | None, int]


class FoxgloveParams(BaseModel):
    """Parameters of the ``foxglove`` observer in a deployment's ``observers:`` block."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    port: int = Field(
        default=DEFAULT_PORT, ge=0, le=65535, description="Serve the live WebSocket here (0: any free port)."
    )
    host: str = Field(default="127.0.0.1", description="Interface the live server binds to.")


class _NewestImages(LatestPerKeyWorker[str, tuple[Thumbnail, int]]):
    """The newest thumbnail of each camera with its hand-over time, published on this worker."""

    def __init__(self, publish: Callable[[Thumbnail, int], None], *, close_timeout_s: float) -> None:
        super().__init__(name="openral-foxglove-images", close_timeout_s=close_timeout_s)
        self._publish = publish

    def handle_item(self, key: str, item: tuple[Thumbnail, int]) -> None:
        self._publish(*item)


class FoxgloveSink(QueuedObserver):
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
        close_timeout_s: How long :meth:`close` waits for each worker to drain.

    Raises:
        ROSConfigError: ``queue_size`` is below 2, or ``flush_interval_s`` is not positive.
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
        if queue_size < 2:
            raise ROSConfigError(f"queue_size must be at least 2, got {queue_size}", field="queue_size")
        self._offset_ns = time.time_ns() - time.monotonic_ns()
        self._context = foxglove.Context()
        self._listen = None if port is None else (host, port)
        self._server: WebSocketServer | None = None

        self._tick_channel = foxglove.Channel(TOPIC_TICK, schema=TICK_SCHEMA, context=self._context)
        self._joint_channel = foxglove.Channel(TOPIC_JOINT_STATES, schema=JOINT_STATE_SCHEMA, context=self._context)
        self._safety_channel = foxglove.Channel(TOPIC_SAFETY, schema=SAFETY_SCHEMA, context=self._context)
        self._camera_channels: dict[str, CompressedImageChannel] = {}

        self._handed_ns: dict[int, int] = {}
        """Hand-over time of each queued tick, by the tick's ``id`` (the queue holds the tick, so the id is unique)."""
        self._finished = False
        self.ticks_published = 0
        """Ticks whose messages were logged."""
        self.images_published = 0
        """Thumbnails logged."""
        self._images = _NewestImages(self._publish_image, close_timeout_s=close_timeout_s)
        super().__init__(
            name="openral-foxglove",
            max_queue=queue_size,
            flush_interval_s=flush_interval_s,
            close_timeout_s=close_timeout_s,
        )
        self._images.start()

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
    def from_config(cls, params: Mapping[str, Any], context: ObserverContext) -> FoxgloveSink:
        """Plugin constructor (observer ``foxglove``); ``params`` are validated as :class:`FoxgloveParams`.

        Images come from the ``thumbnails`` observer. Errors name ``context.option`` (``--foxglove``)
        when the entry stands for one.

        Raises:
            ROSConfigError: A wrong parameter (named with the allowed keys).
        """
        config = validate_model(FoxgloveParams, dict(params), field_prefix=context.option or "observers[].params")
        return cls(port=config.port, host=config.host)

    @property
    def context(self) -> foxglove.Context:
        """The Foxglove context the channels log into (attach more sinks to it)."""
        return self._context

    # -- what the CLI and tests read ------------------------------------------------------

    @property
    def port(self) -> int | None:
        """The port the live server listens on (the real one when 0 was asked), ``None`` without a server."""
        return None if self._server is None else self._server.port

    @property
    def app_url(self) -> str | None:
        """A Foxglove app link that opens this live server, ``None`` without a server."""
        return None if self._server is None else self._server.app_url()

    @property
    def dropped(self) -> int:
        """Ticks dropped because the queue was full."""
        return self.overflowed

    @property
    def images_replaced(self) -> int:
        """Thumbnails replaced by a newer one of the same camera before they were published."""
        return self._images.replaced

    @property
    def publish_errors(self) -> int:
        """Ticks and thumbnails whose publishing failed."""
        return self.errors + self._images.errors

    # -- tick thread and thumbnail worker ---------------------------------------------------

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Hand one tick over to the worker (tick thread; never blocks on I/O, touches no pixels)."""
        if self._finished:
            return
        self._handed_ns[id(tick)] = time.monotonic_ns()
        super().on_tick(tick, world)

    def on_overflow(self, tick: TickResult) -> None:
        self._handed_ns.pop(id(tick), None)

    def on_thumbnail(self, thumb: Thumbnail) -> None:
        """Keep a camera's newest thumbnail for the image worker (called on the runner's thumbnail thread)."""
        if not self._finished:
            self._images.offer(thumb.sensor_id, (thumb, time.monotonic_ns()))

    def close(self) -> None:
        """Publish what was handed over, close the channels and stop the server. Idempotent."""
        if self._finished:
            return
        self._finished = True
        super().close()
        self._images.close()
        self._handed_ns.clear()  # ticks offered while closing were never queued
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

    # -- workers --------------------------------------------------------------------------------

    def handle_tick(self, tick: TickResult, world: WorldState | None) -> None:
        handed_ns = self._handed_ns.pop(id(tick), None)
        joints = None if world is None else world.joint_state
        self._publish_tick((tick, joints, time.monotonic_ns() if handed_ns is None else handed_ns))

    def _publish_tick(self, item: _Item) -> None:
        tick, joints, handed_ns = item
        log_time = handed_ns + self._offset_ns
        stamp = _stamp(log_time)
        record = tick.model_dump(mode="json")
        self._tick_channel.log(_dumps({"timestamp": stamp, **record, "dropped": self.dropped}), log_time=log_time)
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
            events.append((SAFETY_KIND_WITHHELD, record["withheld_reason"]))
        for kind, reason in events:
            self._safety_channel.log(
                _dumps(
                    {
                        "timestamp": stamp,
                        "kind": kind,
                        "reason": reason,
                        **{name: record[name] for name in _SAFETY_TICK_FIELDS},
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
    return Timestamp(*divmod(wall_ns, 1_000_000_000))


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
