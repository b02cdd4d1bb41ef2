"""``RolloutRecorder``: the tick stream of a runner, recorded as episodes of a LeRobotDataset.

It is a queued observer: the tick thread hands it the tick's result and the world state the skill
saw (references, nothing copied); its worker turns each tick inside an episode into one dataset
row and feeds each camera's frame (the very frame the skill saw) to that camera's video encoder.

Per row: ``observation.state`` is the measured joint state of the tick; ``action`` is the target
the robot was commanded to after safety (the action sent, or, when the tick's action was
withheld, the target it kept holding); ``openral.*`` columns keep what really happened (tick
stamp, lateness, requested action, why an action was withheld, each camera's capture stamp,
sequence number and age, the tick's trace and span id).

A deployment lists it as the ``lerobot_dataset`` entry of its ``observers:`` block
(:meth:`RolloutRecorder.from_config`, params :class:`LeRobotDatasetParams`): building it checks the
parameters and opens nothing; :meth:`RolloutRecorder.start` (the runner calls it at activation)
opens the dataset folder.

The first failure to write (a full or read-only disk, an encoder that died) stops the recording:
the episode under way is discarded, the committed ones stay as they are, nothing more is
recorded, :attr:`RolloutRecorder.failure` says why and ``on_failure`` is called (the CLI stops the
run with it). It is logged on one line; the traceback only at debug level.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Final, Literal, Self

import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import RobotEnvironment, RobotManifest, ROSConfigError, ROSRuntimeError, TickResult, WorldState
from openral_core.config import validate_model
from openral_core.config_files import resolve_user_path
from openral_dataset import schema
from openral_dataset.episode import EpisodeSummary
from openral_dataset.writer import LeRobotDatasetSink
from openral_observability import metrics, semconv
from openral_observability.queued_observer import QueuedObserver

_log = structlog.get_logger(__name__)

_MIRRORED: Final = {tick_column.tick_field for tick_column in schema.TICK_COLUMNS}
_ROOT_FIELD: Final = "observers[].params.root"


class LeRobotDatasetParams(BaseModel):
    """Parameters of the ``lerobot_dataset`` observer in a deployment's ``observers:`` block."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    root: Path = Field(description="The dataset folder (relative to the deployment file's folder); created at start.")
    resume: bool = Field(default=False, description="Add episodes to the dataset already there.")
    vcodec: Literal["libsvtav1", "h264"] = Field(default="libsvtav1", description="Video codec of the cameras.")


class RolloutRecorder(QueuedObserver):
    """Records the ticks between ``episode_start`` and ``episode_end`` into ``sink``.

    Pass it to ``HardwareRunner(recorder=...)``; the runner's ``episode_start(task)`` and
    ``episode_end(success=...)`` mark the episodes, and closing the runner finalizes the dataset.

    Args:
        sink: Where episodes go.
        joint_names: The order of the state vector (the robot manifest's joints, or a simulator's
            state names); the action's order is the sink's.
        max_queue: Ticks held for the worker before the oldest is dropped (and counted).
    """

    def __init__(self, sink: LeRobotDatasetSink, *, joint_names: Sequence[str], max_queue: int = 4096) -> None:
        self.sink = sink
        self.joint_names = list(joint_names)
        self.episodes: list[EpisodeSummary] = []
        self.dropped_ticks = 0
        """Ticks inside an episode that never reached the dataset (the queue overflowed)."""
        self.failure: ROSRuntimeError | None = None
        """Why recording stopped early (``None`` while it works); the committed episodes are intact."""
        self.on_failure: Callable[[], None] | None = None
        """Called once, on the worker thread, when recording stops early (e.g. a runner's ``request_stop``)."""
        self._held: list[float] | None = None
        self._state: list[float] | None = None
        self._announce: tuple[int, str] | None = None
        self._ends = threading.Condition()
        self._ends_queued = 0
        self._ends_done = 0
        super().__init__(name="openral-recorder", max_queue=max_queue)

    @classmethod
    def from_config(
        cls,
        params: Mapping[str, Any],
        *,
        robot: RobotManifest,
        env: RobotEnvironment,
        base_dir: Path | None = None,
        option: str | None = None,
    ) -> RolloutRecorder:
        """Plugin constructor (observer ``lerobot_dataset``): ``params`` are :class:`LeRobotDatasetParams`.

        Records ``robot``'s joints and one video per sensor of ``env`` at the tick rate. Opens
        nothing: the dataset folder is opened (created, or checked and resumed) by :meth:`start`.
        ``option`` is the command-line option the entry stands for (``--dataset-out``): errors name it.

        Raises:
            ROSConfigError: A wrong parameter (named with the allowed keys); a tick rate that is not
                a whole number (a dataset's fps is); a sensor id that cannot name a video folder.
        """
        config = validate_model(LeRobotDatasetParams, dict(params), field_prefix="observers[].params")
        if not math.isclose(env.rate_hz, round(env.rate_hz)):
            raise ROSConfigError(
                f"a dataset records whole frames per second; the tick rate is {env.rate_hz:g} Hz",
                field="rate_hz",
                hint="use a whole number of Hz to record",
            )
        field = option or _ROOT_FIELD
        sink = LeRobotDatasetSink(
            resolve_user_path(config.root, base_dir, field=field),
            fps=round(env.rate_hz),
            robot_type=robot.robot_id,
            joint_names=robot.joint_names,
            cameras=[schema.CameraSpec(s.sensor_id, s.width or 0, s.height or 0) for s in env.sensors],
            vcodec=config.vcodec,
            resume=config.resume,
            field=field,
            defer_open=True,
        )
        return cls(sink, joint_names=robot.joint_names)

    def start(self) -> None:
        """Open the dataset folder (the runner calls this at activation, before the first tick). Idempotent.

        A recorder given a sink that is already open has nothing to do.

        Raises:
            ROSConfigError: What :meth:`LeRobotDatasetSink.open` raises: a folder holding other files,
                a dataset there without ``resume`` or one that cannot be resumed, a folder that
                cannot be written.
        """
        self.sink.open()

    def finalize(self) -> None:
        """Write what is queued, commit or discard the open episode, and close the dataset."""
        self.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.finalize()

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        with self._ends:
            self._ends_queued += 1
        super().on_episode_end(episode_idx, success=success, keep=keep)

    def wait_for_commit(self, timeout_s: float = 300.0) -> bool:
        """Block until every episode end queued so far is committed or discarded, or recording stopped.

        Returns:
            ``False`` if that did not happen within ``timeout_s``.
        """
        with self._ends:
            return self._ends.wait_for(
                lambda: self._ends_done >= self._ends_queued or self.failure is not None, timeout_s
            )

    @property
    def repeated_frames(self) -> int:
        """Frames repeated in videos because an encoder fell behind, over every episode so far."""
        return sum(sum(e.repeated_frames.values()) for e in self.episodes)

    # -- worker ----------------------------------------------------------------------------

    def on_overflow(self, tick: TickResult) -> None:
        if tick.step_idx is not None:
            self.dropped_ticks += 1
            metrics.add(semconv.METRIC_RECORDING_DROPPED_TICKS)

    def handle_episode_start(self, episode_idx: int, task: str) -> None:
        if self.failure is not None:
            return
        self._held = None
        try:
            dataset_idx = self.sink.begin_episode(task)
        except Exception as exc:
            self._fail(exc)
            return
        self._announce = (dataset_idx, task)  # logged with its first row: the episode is being recorded then

    def handle_episode_end(self, episode_idx: int, *, success: bool, keep: bool) -> None:
        try:
            if self.sink.episode_open:
                self._end_episode(success=success, keep=keep and self.failure is None)
        except Exception as exc:
            self._fail(exc)
        finally:
            with self._ends:
                self._ends_done += 1
                self._ends.notify_all()

    def _end_episode(self, *, success: bool, keep: bool) -> None:
        summary = self.sink.end_episode(keep=keep, success=success)
        self.episodes.append(summary)
        if summary.committed:
            metrics.record_histogram_ms(semconv.METRIC_RECORDING_EPISODE_CLOSE, summary.close_s * 1e3)
        _log.info(
            "episode committed" if summary.committed else "episode discarded",
            episode=summary.episode_idx,
            frames=summary.frames,
            close_s=round(summary.close_s, 3),
        )

    def handle_tick(self, tick: TickResult, world: WorldState | None) -> None:
        if self.failure is not None or not self.sink.episode_open or tick.step_idx is None:
            return  # stopped, or between episodes (a simulator's reset tick included)
        try:
            self._record_tick(tick, world)
        except Exception as exc:
            self._fail(exc)
            try:
                self.sink.end_episode(keep=False)  # the episode under way is lost; the committed ones stay
            except Exception as discard_exc:
                _log.debug("discarding the episode under way failed", exc_info=discard_exc)

    def _record_tick(self, tick: TickResult, world: WorldState | None) -> None:
        state = self._measured_state(world)
        if state is None:
            return  # nothing measured yet: no row can say where the robot was
        if tick.action_applied and tick.sent_action is not None:
            self._held = list(tick.sent_action)
        action = self._held if self._held is not None else self._hold_default(state)
        trace_id, span_id = _ids(tick.trace_context)
        mirrored = tick.model_dump(mode="json", include=_MIRRORED)
        row: dict[str, Any] = {schema.STATE: state, schema.ACTION: action}
        for tick_column in schema.TICK_COLUMNS:
            row[tick_column.column] = mirrored[tick_column.tick_field]  # None: the column's absent value
        row[schema.TRACE_ID] = trace_id
        row[schema.SPAN_ID] = span_id
        if self.sink.environment_state_names and world is not None and world.privileged is not None:
            row[schema.ENVIRONMENT_STATE] = world.privileged.get("environment_state")
        frames = dict(world.image_frames or {}) if world is not None else {}
        for cam in self.sink.cameras:
            frame = frames.get(cam.sensor_id)
            if frame is not None and world is not None:
                row[schema.camera_column(cam.sensor_id, "stamp_ns")] = frame.stamp_ns
                row[schema.camera_column(cam.sensor_id, "seq")] = frame.seq
                row[schema.camera_column(cam.sensor_id, "age_ms")] = (world.stamp_ns - frame.stamp_ns) / 1e6
        self.sink.add_row(row, frames)
        if self._announce is not None:
            _log.info("recording episode", episode=self._announce[0], task=self._announce[1])
            self._announce = None
        metrics.add(semconv.METRIC_RECORDING_FRAMES)
        for cam in self.sink.cameras:
            if row.get(schema.camera_column(cam.sensor_id, "repeated")):
                metrics.add(semconv.METRIC_RECORDING_REPEATED_FRAMES, 1, {semconv.ATTR_SENSOR_ID: cam.sensor_id})

    def report(self) -> dict[str, int]:
        """What the recording has done so far (the worker may still be writing the last ticks)."""
        committed = [e for e in self.episodes if e.committed]
        return {
            "episodes_committed": len(committed),
            "episodes_discarded": len(self.episodes) - len(committed),
            "frames": sum(e.frames for e in committed),
            "repeated_frames": self.repeated_frames,
            "dropped_ticks": self.dropped_ticks,
            "errors": self.errors,
        }

    def handle_close(self) -> None:
        if self.sink.episode_open:
            # The run ended inside an episode (a stop, a fault): what was recorded is kept.
            self.handle_episode_end(-1, success=False, keep=True)
        self.sink.close()

    def _fail(self, exc: Exception) -> None:
        """Stop recording at the first failure: one line in the log, the traceback at debug level."""
        self.errors += 1
        if self.failure is not None:
            return
        root = str(self.sink.root)
        text = str(exc) if root in str(exc) else f"recording into {root} failed: {exc}"
        self.failure = ROSRuntimeError(text)
        _log.error("recording stopped", dataset=root, error=text)
        _log.debug("recording stopped", exc_info=exc)
        with self._ends:
            self._ends.notify_all()
        if self.on_failure is not None:
            self.on_failure()

    def _hold_default(self, state: list[float]) -> list[float]:
        """The target before any action was sent: the measured joints, or zeros for a non-joint action space."""
        if self.sink.action_names == self.joint_names:
            return state
        return [0.0] * len(self.sink.action_names)

    def _measured_state(self, world: WorldState | None) -> list[float] | None:
        joints = None if world is None else world.joint_state
        if joints is not None:
            if list(joints.names) == self.joint_names:
                self._state = list(joints.positions)
            else:
                by_name = dict(zip(joints.names, joints.positions, strict=True))
                self._state = [by_name[name] for name in self.joint_names]
        return self._state


def _ids(traceparent: str | None) -> tuple[str | None, str | None]:
    """Trace and span id from a W3C ``traceparent`` value (``None`` when the tick was not traced)."""
    if not traceparent:
        return None, None
    parts = traceparent.split("-")
    if len(parts) != 4:
        return None, None
    return parts[1], parts[2]
