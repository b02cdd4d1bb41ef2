"""The deployment file: ``RobotEnvironment`` and the blocks it is made of."""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any, Self

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, field_validator, model_validator

from openral_core.actions import SafetyMode, check_workspace_box
from openral_core.config import load_model_yaml
from openral_core.execution import ExecutorConfig
from openral_core.frames import FrameEncoding

_ID_PATTERN = r"^[A-Za-z][A-Za-z0-9_\-]*$"

MAX_CAMERA_FPS = 1000.0
"""Highest frame or publish rate a sensor may be configured for."""

THUMBNAILS_OBSERVER = "thumbnails"
"""The observer that encodes camera thumbnails once for every viewer (``thumbnail_hz`` is short for it)."""

MAX_IMAGE_SIDE = 16384
"""Largest image width or height accepted (16K)."""

CPU_SETSIZE = 1024
"""CPU ids the kernel's affinity mask can name (glibc's ``CPU_SETSIZE``)."""


class SensorReaderBackend(StrEnum):
    """The built-in capture backends (plugins in ``openral.sensor_backends``).

    ``SensorReaderConfig.backend`` is any plugin id, checked against the registry when the
    deployment is built, so a backend another package registers is used like these.
    """

    OPENCV_THREAD = "opencv_thread"
    GSTREAMER = "gstreamer"
    ROS2_IMAGE = "ros2_image"
    MUJOCO_CAMERA = "mujoco_camera"
    HOLOSCAN = "holoscan"  # reserved: no implementation yet


class GarbageCollection(StrEnum):
    """When Python's cyclic garbage collector may run during ``run()``.

    ``between_ticks``: automatic collection is paused for the run (objects alive at its start
    are frozen out of every collection) and the young generations are collected in the idle time
    after a tick, so no collection pause lands inside a tick. ``automatic``: Python's own
    thresholds, which can stop any thread, mid-tick, for milliseconds.
    """

    BETWEEN_TICKS = "between_ticks"
    AUTOMATIC = "automatic"


class DeadlineOverrunPolicy(StrEnum):
    """What the runner does with an action that is ready after its tick's deadline.

    ``warn`` sends it and counts the miss; ``drop`` withholds it; ``raise`` withholds it,
    leaves the robot holding, stops the loop and raises ``ROSDeadlineMissed``.
    """

    WARN = "warn"
    DROP = "drop"
    RAISE = "raise"


def _allow_yaml_null(schema: dict[str, Any]) -> None:
    """The schema of a plugin name also accepts YAML ``null`` (read as the plugin "null")."""
    pattern = schema.pop("pattern", None)
    kind = schema.pop("type", "string")
    schema["anyOf"] = [{"type": kind, **({"pattern": pattern} if pattern else {})}, {"type": "null"}]


_NULLABLE_NAME = _allow_yaml_null


def _null_name(value: Any) -> Any:
    """YAML reads an unquoted ``null`` plugin name as ``None``; the plugin is called "null"."""
    return "null" if value is None else value


class _Block(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SensorReaderConfig(_Block):
    """One sensor of the deployment.

    ``publish_to_ros`` and ``publish_topic`` go together: a ROS tee needs a topic, and a
    topic means nothing without the tee.
    """

    sensor_id: str = Field(pattern=_ID_PATTERN)
    backend: str = Field(
        default=SensorReaderBackend.OPENCV_THREAD.value,
        pattern=_ID_PATTERN,
        description="a plugin in the openral.sensor_backends entry-point group",
        json_schema_extra={"examples": [b.value for b in SensorReaderBackend if b is not SensorReaderBackend.HOLOSCAN]},
    )
    required: bool = True
    max_age_ms: float = Field(default=100.0, gt=0)
    fps: float = Field(default=30.0, gt=0, le=MAX_CAMERA_FPS)
    width: int | None = Field(default=None, ge=1, le=MAX_IMAGE_SIDE)
    height: int | None = Field(default=None, ge=1, le=MAX_IMAGE_SIDE)
    encoding: FrameEncoding = FrameEncoding.BGR8
    backend_params: dict[str, Any] = Field(default_factory=dict)
    publish_to_ros: bool = False
    publish_topic: str | None = None
    publish_rate_hz: float | None = Field(default=None, gt=0, le=MAX_CAMERA_FPS)

    @model_validator(mode="after")
    def _ros_tee(self) -> Self:
        if self.publish_to_ros and not self.publish_topic:
            raise ValueError("publish_to_ros is true but publish_topic is empty: name the ROS topic to publish")
        if self.publish_topic and not self.publish_to_ros:
            raise ValueError("publish_topic is set but publish_to_ros is false: set publish_to_ros: true")
        return self


class SyncConfig(_Block):
    """Cameras whose frames must be captured together each tick.

    Attributes:
        sensors: Sensor ids read as one set (at least two).
        max_skew_ms: Largest spread of capture stamps within the set.
        timeout_ms: How long a tick may wait for lagging cameras before the set counts as failed.
    """

    sensors: list[str] = Field(min_length=2)
    max_skew_ms: float = Field(default=10.0, gt=0)
    timeout_ms: float = Field(default=15.0, gt=0)


class HalConfig(_Block):
    """Which robot and which adapter drives it.

    ``robot_id`` names a manifest (``robots/<robot_id>/robot.yaml``); ``adapter`` names a
    plugin in ``openral.hals`` (``mujoco_twin``, ...); ``params`` go to the adapter's own
    typed parameter model.
    """

    robot_id: str = Field(pattern=_ID_PATTERN)
    adapter: str = Field(default="mujoco_twin", pattern=_ID_PATTERN, json_schema_extra=_NULLABLE_NAME)
    params: dict[str, Any] = Field(default_factory=dict)

    @field_validator("adapter", mode="before")
    @classmethod
    def _yaml_null(cls, value: Any) -> Any:
        return _null_name(value)


class TaskSpec(_Block):
    """What the robot should do, in words the skill understands."""

    instruction: str = ""
    task_id: str | None = None


class VLASpec(_Block):
    """The skill (policy) to run.

    Attributes:
        id: Name of a plugin in ``openral.skills`` (``hello``, ...).
        manifest: Optional rSkill manifest (``rskill.yaml``) checked for licence before loading.
        accept_licenses: SPDX ids this deployment accepts; ``None`` accepts the built-in open list.
        params: Passed to the skill's own typed parameter model.
    """

    id: str = Field(pattern=_ID_PATTERN)
    manifest: str | None = None
    accept_licenses: list[str] | None = None
    params: dict[str, Any] = Field(default_factory=dict)


class SafetyConfig(_Block):
    """Which safety client checks every action, and how.

    ``client: null`` disables checking (the runner warns at start).
    """

    client: str = Field(default="envelope", pattern=_ID_PATTERN, json_schema_extra=_NULLABLE_NAME)
    mode: SafetyMode = SafetyMode.CLAMP
    max_joint_speed_factor: float = Field(default=1.0, gt=0, le=1.0)
    workspace_min: tuple[float, float, float] | None = None
    workspace_max: tuple[float, float, float] | None = None

    @field_validator("client", mode="before")
    @classmethod
    def _yaml_null(cls, value: Any) -> Any:
        return _null_name(value)

    @model_validator(mode="after")
    def _box(self) -> Self:
        check_workspace_box(self.workspace_min, self.workspace_max)
        return self


class RealtimeConfig(_Block):
    """Real-time knobs applied at activation; one that cannot be applied is a warning.

    Attributes:
        sched_fifo_priority: SCHED_FIFO priority (1..99) for the tick thread; ``None`` leaves the policy.
        cpu_affinity: CPUs the process may run on; ``None`` leaves affinity alone.
        switch_interval_s: ``sys.setswitchinterval`` value; a short interval bounds how long
            another Python thread can hold the GIL past a tick's wake-up.
        lock_memory: ``mlockall`` so page faults cannot stall a tick.
        garbage_collection: When the cyclic garbage collector may run (see :class:`GarbageCollection`).
    """

    sched_fifo_priority: int | None = Field(default=None, ge=1, le=99)
    cpu_affinity: list[Annotated[int, Field(ge=0, lt=CPU_SETSIZE)]] | None = Field(default=None, min_length=1)
    switch_interval_s: float | None = Field(default=None, gt=0, le=0.1)
    lock_memory: bool = False
    garbage_collection: GarbageCollection = GarbageCollection.BETWEEN_TICKS


class ObserverConfig(_Block):
    """One observer: a plugin in ``openral.observers`` that watches every tick (recorders, viewers, ...).

    ``params`` go to the observer's own typed parameter model.
    """

    id: str = Field(pattern=_ID_PATTERN)
    params: dict[str, Any] = Field(default_factory=dict)
    _option: str | None = PrivateAttr(default=None)

    @classmethod
    def shorthand(cls, observer_id: str, params: dict[str, Any], *, option: str) -> ObserverConfig:
        """The entry a command-line ``option`` stands for; its observer names the option in its errors.

        Not part of the file format: a deployment file cannot set it.
        """
        entry = cls(id=observer_id, params=params)
        entry._option = option
        return entry

    @property
    def option(self) -> str | None:
        """The command-line option this entry stands for (``--dataset-out``), ``None`` for a file's own entry."""
        return self._option


class Watched(BaseModel):
    """The ``observers:`` block (and its ``thumbnail_hz`` shorthand) of a loop: a deployment or a scene.

    Both build their observers from these entries through the same builder, so an entry means the
    same on a robot and in simulation.
    """

    observers: list[ObserverConfig] = Field(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _thumbnail_shorthand(cls, data: Any) -> Any:
        """``thumbnail_hz: R`` is short for an ``observers`` entry ``{id: thumbnails, params: {rate_hz: R}}``."""
        if not isinstance(data, dict) or "thumbnail_hz" not in data:
            return data
        data = dict(data)
        rate = data.pop("thumbnail_hz")
        if isinstance(rate, bool) or not isinstance(rate, int | float) or not 0 <= rate <= MAX_CAMERA_FPS:
            raise ValueError(
                f"thumbnail_hz must be a number from 0 to {MAX_CAMERA_FPS:g}, got {rate!r} "
                "(it is short for observers: [{id: thumbnails, params: {rate_hz: ...}}])"
            )
        observers = list(data.get("observers") or [])
        named = [o.get("id") if isinstance(o, dict) else getattr(o, "id", None) for o in observers]
        if rate > 0 and THUMBNAILS_OBSERVER not in named:
            observers.append({"id": THUMBNAILS_OBSERVER, "params": {"rate_hz": float(rate)}})
            data["observers"] = observers
        return data


DEFAULT_SENSOR_READY_TIMEOUT_S = 10.0
"""How long a run waits for its required sensors' first fresh frames unless ``faults:`` says otherwise."""


class FaultPolicy(_Block):
    """How many consecutive failed ticks of each kind end the run safely.

    A failed tick (stale required sensor, failed ``read_state``, skill exception) always
    withholds its action; after this many in a row the runner stops and holds the robot.
    """

    max_consecutive_failures: int = Field(default=5, ge=1)
    sensor_ready_timeout_s: float = Field(
        default=DEFAULT_SENSOR_READY_TIMEOUT_S,
        gt=0,
        le=600,
        allow_inf_nan=False,
        description="how long a run waits, before its first tick, for every required sensor to deliver a frame "
        "within its max_age_ms; a sensor that does not fails the start with its measured frame age",
    )


class TakeoverTrigger(StrEnum):
    """How a person passes control between the policy and the takeover skill."""

    KEY = "key"
    """A key in the terminal that runs the command."""
    CONSOLE = "console"
    """The web console's takeover button."""


RESERVED_KEYS = frozenset("nrqs")
"""Keys the commands already use (next, re-record, quit, save a highlight): a takeover key may not be one."""


class TakeoverConfig(_Block):
    """A skill a person drives (a leader arm) that can take control from the policy mid-run, and give it back.

    While the person drives, their skill's actions pass the same safety envelope; switching either
    way never jumps the robot (the first commands move at most one envelope step per tick towards
    the new skill's target). Recorded rows say which ticks were the person's.
    """

    skill: str = Field(pattern=_ID_PATTERN, description="The skill the person drives, e.g. leader_arm.")
    params: dict[str, Any] = Field(default_factory=dict, description="The takeover skill's parameters.")
    via: list[TakeoverTrigger] = Field(
        default_factory=lambda: [TakeoverTrigger.KEY, TakeoverTrigger.CONSOLE],
        min_length=1,
        description="How control passes: the terminal key, the console's button, or both.",
    )
    key: str = Field(default="t", min_length=1, max_length=1, description="The terminal key that toggles control.")
    policy_labels: bool = Field(
        default=True,
        description="The policy keeps inferring while the person drives; its proposed action is recorded beside "
        "theirs (DAgger labels).",
    )

    @field_validator("key")
    @classmethod
    def _free_key(cls, key: str) -> str:
        if key in RESERVED_KEYS or not key.isprintable() or key.isspace():
            raise ValueError(
                f"takeover.key {key!r} is taken or unprintable: n, r, q and s are the recording keys; "
                "pick another letter"
            )
        return key


class RobotEnvironment(Watched, _Block):
    """A deployment: robot, sensors, skill, task, rate and policies. Loaded from YAML."""

    name: str = Field(default="deployment", min_length=1)
    hal: HalConfig
    vla: VLASpec
    task: TaskSpec = Field(default_factory=TaskSpec)
    sensors: list[SensorReaderConfig] = Field(default_factory=list)
    sync: SyncConfig | None = None
    rate_hz: float = Field(default=30.0, gt=0, le=10_000)
    deadline_overrun_policy: DeadlineOverrunPolicy = DeadlineOverrunPolicy.WARN
    latency_budget_ms: float | None = Field(default=None, gt=0)
    safety: SafetyConfig = Field(default_factory=SafetyConfig)
    executor: ExecutorConfig = Field(default_factory=ExecutorConfig)
    """How a chunking skill's chunks are executed (skills with chunk size 1 do not use it)."""
    realtime: RealtimeConfig = Field(default_factory=RealtimeConfig)
    faults: FaultPolicy = Field(default_factory=FaultPolicy)
    takeover: TakeoverConfig | None = None
    """A skill a person can take control with mid-run (a leader arm); none by default."""

    @model_validator(mode="after")
    def _unique_sensor_ids(self) -> Self:
        seen: set[str] = set()
        for index, sensor in enumerate(self.sensors):
            if sensor.sensor_id in seen:
                raise ValueError(
                    f"sensors[{index}].sensor_id '{sensor.sensor_id}' is used twice: give each sensor its own id"
                )
            seen.add(sensor.sensor_id)
        if self.sync is not None:
            for index, sensor_id in enumerate(self.sync.sensors):
                if sensor_id not in seen:
                    raise ValueError(
                        f"sync.sensors[{index}] '{sensor_id}' is not a declared sensor; declared: {sorted(seen)}"
                    )
            if len(set(self.sync.sensors)) != len(self.sync.sensors):
                raise ValueError("sync.sensors lists a sensor twice")
        return self

    @property
    def period_s(self) -> float:
        """Tick period in seconds."""
        return 1.0 / self.rate_hz

    @classmethod
    def from_yaml(cls, path: str | Path, *, field: str | None = None) -> RobotEnvironment:
        """Load and validate a deployment file.

        Args:
            field: The option that named the file (``--config``), named by file-level errors.

        Raises:
            ROSConfigError: The file is missing, not a regular file, not UTF-8 YAML, or a field is
                wrong; the message names the field and the fix.
        """
        return load_model_yaml(cls, Path(path), field=field)
