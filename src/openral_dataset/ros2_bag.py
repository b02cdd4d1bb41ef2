"""``Ros2BagWriter``: the session as a ROS 2 bag (MCAP, profile ``ros2``, CDR), readable by ROS 2 tools and Foxglove.

A tick observer. Message definitions and CDR serialisation come from the ``rosbags`` typestore
(ROS 2 Humble), never written by hand. Topics:

- ``/joint_states`` (``sensor_msgs/msg/JointState``): the measured state of every tick.
- ``/openral/command/requested`` and ``/openral/command/sent`` (``sensor_msgs/msg/JointState``,
  positions): what the skill asked for, and what reached the robot after safety.
- ``/camera/<sensor_id>/compressed`` (``sensor_msgs/msg/CompressedImage``): the runner's JPEG
  thumbnails (subscribed, so a frame is encoded once for every viewer).
- ``/openral/tick`` and ``/openral/episode`` (``std_msgs/msg/String``, JSON): each tick's record
  (its ``TickResult`` fields that have a value: timings, lateness, why an action was withheld,
  trace context, episode and step, a simulator's reward; the actions and the start are on their
  own topics and in the log time) and each episode boundary.

The deployment file rides along as an attachment. Stamps are wall-clock nanoseconds: monotonic
stamps plus one offset taken when the bag opens, so intervals stay exact. A bag cut short by a
crash has no summary but stays readable by a streaming reader, up to its last message.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any, Final

from pydantic import BaseModel, ConfigDict, Field

from openral_core import ObserverContext, ROSConfigError, ROSDependencyMissing, TickResult, WorldState
from openral_core.config import validate_model
from openral_core.config_files import read_config_file, resolve_user_path
from openral_observability.observer import Thumbnail
from openral_observability.queued_observer import QueuedObserver

try:
    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore
except ImportError as exc:
    raise ROSDependencyMissing(exc.name or "rosbags", extra="dataset", needed_for="ROS 2 bags") from exc

JOINT_STATE: Final = "sensor_msgs/msg/JointState"
COMPRESSED_IMAGE: Final = "sensor_msgs/msg/CompressedImage"
STRING: Final = "std_msgs/msg/String"
TOPIC_JOINT_STATES: Final = "/joint_states"
TOPIC_REQUESTED: Final = "/openral/command/requested"
TOPIC_SENT: Final = "/openral/command/sent"
TOPIC_TICK: Final = "/openral/tick"
TOPIC_EPISODE: Final = "/openral/episode"
TOPIC_CAMERA: Final = "/camera/{sensor_id}/compressed"


class Ros2BagParams(BaseModel):
    """Parameters of the ``ros2_bag`` observer in a deployment's ``observers:`` block."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    path: str = Field(description="The .mcap file to create (relative to the deployment file's folder).")
    overwrite: bool = Field(default=False, description="Replace an existing file.")
    attach: str | None = Field(
        default=None, description="A file attached to the bag, such as the deployment (relative to its folder)."
    )


class Ros2BagWriter(QueuedObserver):
    """Writes every tick, episode boundary and camera thumbnail of a run into one ROS 2 MCAP bag.

    Args:
        path: The ``.mcap`` file, created by :meth:`start`.
        joint_names: The robot's joints (names of the command messages).
        deployment: The deployment file, attached to the bag (read now, as a configuration file).
        overwrite: Replace an existing file instead of refusing.
        field: The option or field that named the file, for errors.
        attach_field: The option or field that named ``deployment``, for errors.

    Raises:
        ROSConfigError: The file exists (without ``overwrite``) or its folder is missing or read-only;
            ``deployment`` is not a regular UTF-8 file of at most 1 MiB.
    """

    def __init__(
        self,
        path: Path,
        *,
        joint_names: list[str],
        deployment: Path | None = None,
        overwrite: bool = False,
        field: str = "--mcap",
        attach_field: str = "--config",
    ) -> None:
        _check_target(path, overwrite=overwrite, field=field)
        # Read now, as a configuration file (regular, at most 1 MiB, UTF-8): a device, a FIFO or a
        # huge file is refused before the bag exists, and starting reads nothing more.
        self._attachment = (
            None
            if deployment is None
            else (deployment.name, read_config_file(deployment, field=attach_field).encode("utf-8"))
        )
        self.path = path
        self.joint_names = list(joint_names)
        self._overwrite = overwrite
        self._field = field
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._store = get_typestore(Stores.ROS2_HUMBLE)
        self._offset_ns = time.time_ns() - time.monotonic_ns()
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self._thumbs: dict[str, Thumbnail] = {}
        self._thumb_lock = threading.Lock()
        self.messages = 0
        super().__init__(name="openral-rosbag", max_queue=4096)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], context: ObserverContext) -> Ros2BagWriter:
        """Plugin constructor (observer ``ros2_bag``): ``params`` are ``path`` (relative to the loop's
        ``base_dir``), ``overwrite`` and ``attach``. Camera images come from the ``thumbnails`` observer.
        Errors name ``context.option`` (``--mcap``) when the entry stands for one.

        Raises:
            ROSConfigError: A wrong parameter, or the file could not be created there.
        """
        config = validate_model(Ros2BagParams, dict(params), field_prefix="observers[].params")
        field = context.option or "observers[].params.path"
        path = resolve_user_path(config.path, context.base_dir, field=field)
        attach = None
        if config.attach is not None:
            attach = resolve_user_path(config.attach, context.base_dir, field="observers[].params.attach")
        return cls(
            path,
            joint_names=list(context.joint_names),
            overwrite=config.overwrite,
            field=field,
            deployment=attach,
            attach_field="observers[].params.attach",
        )

    def start(self) -> None:
        """Create the file and write the bag's header (the runner calls this at activation). Idempotent.

        Building the writer only checks that the file could be created, so validating a
        deployment never creates, truncates or takes a bag's name.

        Raises:
            ROSConfigError: The file exists now (without ``overwrite``) or cannot be created.
        """
        if self._file is not None:
            return
        try:
            self._file = open(self.path, "wb" if self._overwrite else "xb")  # noqa: SIM115  (closed in handle_close)
        except OSError as exc:
            raise ROSConfigError(
                f"cannot create the ROS 2 bag {self.path}: {exc}",
                field=self._field,
                hint="choose a new file in a writable folder",
            ) from exc
        self._offset_ns = time.time_ns() - time.monotonic_ns()
        self._writer = Writer(self._file)
        self._writer.start(profile="ros2", library="openral")
        if self._attachment is not None:
            name, data = self._attachment
            now = time.time_ns()
            self._writer.add_attachment(
                create_time=now,
                log_time=now,
                name=name,
                media_type="application/yaml",
                data=data,
            )

    # -- observer hooks ----------------------------------------------------------------------

    def on_thumbnail(self, thumb: Thumbnail) -> None:
        """Keep a camera's newest thumbnail; the worker writes it with the next tick."""
        with self._thumb_lock:
            self._thumbs[thumb.sensor_id] = thumb

    def handle_tick(self, tick: TickResult, world: WorldState | None) -> None:
        log_ns = tick.start_ns + self._offset_ns
        joints = None if world is None else world.joint_state
        if joints is not None:
            stamp = joints.stamp_ns + self._offset_ns
            self._write(
                TOPIC_JOINT_STATES,
                JOINT_STATE,
                self._joint_state(stamp, joints.names, joints.positions, joints.velocities or []),
                log_ns,
            )
        if tick.requested_action is not None:
            self._write(TOPIC_REQUESTED, JOINT_STATE, self._command(log_ns, tick.requested_action), log_ns)
        if tick.action_applied and tick.sent_action is not None:
            self._write(TOPIC_SENT, JOINT_STATE, self._command(log_ns, tick.sent_action), log_ns)
        self._write(TOPIC_TICK, STRING, self._string(_tick_record(tick)), log_ns)
        self._write_thumbnails(log_ns)

    def _write_thumbnails(self, log_ns: int) -> None:
        with self._thumb_lock:
            thumbs, self._thumbs = self._thumbs, {}
        for thumb in thumbs.values():
            topic = TOPIC_CAMERA.format(sensor_id=thumb.sensor_id)
            self._write(topic, COMPRESSED_IMAGE, self._image(thumb), log_ns)

    def handle_episode_start(self, episode_idx: int, task: str) -> None:
        now = time.time_ns()
        record = {"event": "start", "episode_idx": episode_idx, "task": task}
        self._write(TOPIC_EPISODE, STRING, self._string(record), now)

    def handle_episode_end(self, episode_idx: int, *, success: bool, keep: bool) -> None:
        now = time.time_ns()
        record = {"event": "end", "episode_idx": episode_idx, "success": success, "kept": keep}
        self._write(TOPIC_EPISODE, STRING, self._string(record), now)

    def handle_close(self) -> None:
        if self._file is None or self._writer is None:  # never started: no file was created
            return
        try:
            self._write_thumbnails(time.time_ns())  # the last ones, handed over after the last tick
            self._writer.finish()  # type: ignore[no-untyped-call]
        finally:
            self._file.close()

    # -- messages ----------------------------------------------------------------------------

    def _write(self, topic: str, msgtype: str, message: Any, log_ns: int) -> None:
        if self._writer is None:
            raise RuntimeError("the ROS 2 bag was not started")  # the runner starts observers before ticking
        channel = self._channels.get(topic)
        if channel is None:
            schema = self._schemas.get(msgtype)
            if schema is None:
                text, _ = self._store.generate_msgdef(msgtype, ros_version=2)
                schema = self._schemas[msgtype] = self._writer.register_schema(
                    name=msgtype, encoding="ros2msg", data=text.encode("utf-8")
                )
            channel = self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=schema
            )
        data = self._store.serialize_cdr(message, msgtype)
        self._writer.add_message(
            channel_id=channel, log_time=log_ns, data=bytes(data), publish_time=log_ns, sequence=self._sequence
        )
        self._sequence += 1
        self.messages += 1

    def _header(self, stamp_ns: int, frame_id: str = "") -> Any:
        types = self._store.types
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        return types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
        )

    def _joint_state(self, stamp_ns: int, names: list[str], positions: list[float], velocities: list[float]) -> Any:
        import numpy as np  # noqa: PLC0415  (numpy is a core dependency; the typestore wants arrays)

        return self._store.types[JOINT_STATE](
            header=self._header(stamp_ns),
            name=list(names),
            position=np.asarray(positions, np.float64),
            velocity=np.asarray(velocities, np.float64),
            effort=np.zeros(0, np.float64),
        )

    def _command(self, stamp_ns: int, positions: list[float]) -> Any:
        return self._joint_state(stamp_ns, self.joint_names, positions, [])

    def _image(self, thumb: Thumbnail) -> Any:
        import numpy as np  # noqa: PLC0415

        return self._store.types[COMPRESSED_IMAGE](
            header=self._header(thumb.stamp_ns + self._offset_ns, thumb.frame_id or thumb.sensor_id),
            format="jpeg",
            data=np.frombuffer(thumb.jpeg, np.uint8),
        )

    def _string(self, record: dict[str, Any]) -> Any:
        return self._store.types[STRING](data=json.dumps(record, allow_nan=False, default=str))


NOT_IN_TICK_RECORD: Final = {"start_ns", "requested_action", "sent_action"}
"""``TickResult`` fields the tick record leaves out: the start is the log time, the actions have their own topics."""


def _tick_record(tick: TickResult) -> dict[str, Any]:
    """The record on ``/openral/tick``: each ``TickResult`` field with a value, less :data:`NOT_IN_TICK_RECORD`."""
    return tick.model_dump(mode="json", exclude=NOT_IN_TICK_RECORD, exclude_none=True)


def _check_target(path: Path, *, overwrite: bool, field: str) -> None:
    """Refuse now what creating the bag at start would refuse: an existing file, a missing or read-only folder."""
    hint = "choose a new file in a writable folder"
    if not overwrite and (path.exists() or path.is_symlink()):
        raise ROSConfigError(f"cannot create the ROS 2 bag {path}: the file exists", field=field, hint=hint)
    folder = path.parent
    if not folder.is_dir():
        raise ROSConfigError(f"cannot create the ROS 2 bag {path}: no folder {folder}", field=field, hint=hint)
    if path.is_dir():
        raise ROSConfigError(f"cannot create the ROS 2 bag {path}: it is a folder", field=field, hint=hint)
    if not os.access(folder, os.W_OK):
        raise ROSConfigError(f"cannot create the ROS 2 bag {path}: {folder} is not writable", field=field, hint=hint)
