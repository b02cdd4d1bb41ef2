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

Two other ways to record, one at a time:

* **Continuous** (``episode_every_s``): the episode under way is committed every N seconds of rows
  (N x fps rows: when the next row comes) and that row starts the next part, with the same task,
  while the runner goes on; a crash loses at most the part under way. The runner's ``episode_end``
  commits the last part (shorter, or full) with the episode's outcome; the parts before it have none
  (``keep=False`` throws away only the part under way: the others are committed already).
* **Highlights** (``highlight_s``): nothing is written while an episode runs; the last N seconds of
  rows and frames are held in memory, each frame compressed once by the worker
  (:mod:`openral_dataset.highlight`), and :meth:`RolloutRecorder.save_highlight` (from any thread)
  commits them as one episode, on a thread of their own so the worker goes on filling the ring.
  ``episode_end`` forgets them. As in the other modes, a camera's buffer is held by reference only
  until the worker has taken its tick (every capture backend hands over a new buffer per frame).

The first failure to write (a full or read-only disk, an encoder that died) stops the recording:
the episode under way is discarded, the committed ones stay as they are, nothing more is
recorded, :attr:`RolloutRecorder.failure` says why and ``on_failure`` is called (the CLI stops the
run with it). It is logged on one line; the traceback only at debug level.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Final, Literal, Self

import structlog
from pydantic import BaseModel, ConfigDict, Field, model_validator

from openral_core import (
    ObserverContext,
    ROSConfigError,
    ROSRuntimeError,
    SensorFrame,
    TickResult,
    WorldState,
)
from openral_core.config import validate_model
from openral_core.config_files import resolve_user_path
from openral_dataset import schema
from openral_dataset.episode import EpisodeSummary
from openral_dataset.highlight import MAX_HIGHLIGHT_S, Highlight, HighlightRing
from openral_dataset.video import OverflowPolicy
from openral_dataset.writer import LeRobotDatasetSink
from openral_observability import metrics, semconv
from openral_observability.queued_observer import QueuedObserver

_log = structlog.get_logger(__name__)

_ROOT_FIELD: Final = "observers[].params.root"
MAX_PENDING_SAVES: Final = 4
"""Highlight saves waiting for the saving thread at most (each holds its rows until written)."""


class LeRobotDatasetParams(BaseModel):
    """Parameters of the ``lerobot_dataset`` observer in a deployment's ``observers:`` block."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    root: Path = Field(description="The dataset folder (relative to the deployment file's folder); created at start.")
    resume: bool = Field(default=False, description="Add episodes to the dataset already there.")
    vcodec: Literal["libsvtav1", "h264"] = Field(default="libsvtav1", description="Video codec of the cameras.")
    episode_every_s: float | None = Field(
        default=None,
        gt=0,
        allow_inf_nan=False,
        description="Cut each episode into parts of this many seconds of rows, each committed as it fills.",
    )
    highlight_s: float | None = Field(
        default=None,
        gt=0,
        le=MAX_HIGHLIGHT_S,
        allow_inf_nan=False,
        description="Write nothing but hold the last this many seconds in memory, saved on save_highlight() "
        f"(at most {MAX_HIGHLIGHT_S:g}: the ring is held in memory).",
    )

    @model_validator(mode="after")
    def _one_mode(self) -> Self:
        if self.episode_every_s is not None and self.highlight_s is not None:
            raise ValueError(_BOTH_MODES)
        return self


_BOTH_MODES: Final = (
    "highlight_s and episode_every_s cannot be used together: highlights write only what is saved, "
    "continuous recording writes everything; set one of them"
)


class RolloutRecorder(QueuedObserver):
    """Records the ticks between ``episode_start`` and ``episode_end`` into ``sink``.

    Add it to a runner's observers (``HardwareRunner(recorder=...)`` is short for that); the runner's
    ``episode_start(task)`` and ``episode_end(success=...)`` mark the episodes, and closing the
    runner finalizes the dataset.

    Args:
        sink: Where episodes go. In highlight mode its encoders wait for free slots (frames come
            from memory, as fast as they decode: none should be repeated).
        joint_names: The order of the state vector (the robot manifest's joints, or a simulator's
            state names); the action's order is the sink's.
        max_queue: Ticks held for the worker before the oldest is dropped (and counted).
        episode_every_s: Continuous recording: commit a part every this many seconds of rows.
        highlight_s: Highlights: hold the last this many seconds (at most :data:`MAX_HIGHLIGHT_S`);
            write only what :meth:`save_highlight` asks for.

    Raises:
        ROSConfigError: ``episode_every_s`` or ``highlight_s`` not a positive, finite number of
            seconds or shorter than one frame, ``highlight_s`` longer than :data:`MAX_HIGHLIGHT_S`,
            or both given.
    """

    def __init__(
        self,
        sink: LeRobotDatasetSink,
        *,
        joint_names: Sequence[str],
        max_queue: int = 4096,
        episode_every_s: float | None = None,
        highlight_s: float | None = None,
    ) -> None:
        if episode_every_s is not None and highlight_s is not None:
            raise ROSConfigError(_BOTH_MODES, field="highlight_s")
        self.part_rows = _rows(episode_every_s, sink.fps, "episode_every_s")
        """Rows per part in continuous recording (``None``: one part per episode)."""
        self.episode_every_s = episode_every_s
        """Continuous recording's part length, seconds (``None``: not continuous)."""
        self.highlight_s = highlight_s
        """Seconds a highlight holds (``None``: no highlights; :meth:`save_highlight` refuses)."""
        self.highlight: HighlightRing | None = None
        """The rows held for a highlight (``None`` unless ``highlight_s`` was given)."""
        self._saver: ThreadPoolExecutor | None = None
        highlight_rows = _rows(highlight_s, sink.fps, "highlight_s", maximum=MAX_HIGHLIGHT_S)
        if highlight_rows is not None:
            self.highlight = HighlightRing(highlight_rows)
            self._saver = ThreadPoolExecutor(max_workers=1, thread_name_prefix="openral-highlight")
            sink.overflow = OverflowPolicy.WAIT
        self._saves_pending = 0
        self.sink = sink
        self.joint_names = list(joint_names)
        self.episodes: list[EpisodeSummary] = []
        self.dropped_ticks = 0
        """Ticks inside an episode that never reached the dataset (the queue overflowed)."""
        self.failure: ROSRuntimeError | None = None
        """Why recording stopped early (``None`` while it works); the committed episodes are intact."""
        self.on_failure: Callable[[], None] | None = None
        """Called once, on the worker (or the highlight-saving) thread, when recording stops early
        (e.g. a runner's ``request_stop``)."""
        self._held: list[float] | None = None
        self._state: list[float] | None = None
        self._announce: tuple[int, str] | None = None
        self._task: str | None = None
        """The task of the episode the runner has open (``None`` between episodes)."""
        self._part_filled = 0
        self._ends = threading.Condition()
        self._ends_queued = 0
        self._ends_done = 0
        # Closing waits for the highlights asked for: each may take a few times its length to write.
        close_timeout_s = _wait_s(30.0 + (MAX_PENDING_SAVES * 3 * highlight_s if highlight_s is not None else 0.0))
        self._tick_columns = schema.tick_columns(takeover=sink.takeover)
        self._mirrored = {tick_column.tick_field for tick_column in self._tick_columns}
        super().__init__(name="openral-recorder", max_queue=max_queue, close_timeout_s=close_timeout_s)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], context: ObserverContext) -> RolloutRecorder:
        """Plugin constructor (observer ``lerobot_dataset``): ``params`` are :class:`LeRobotDatasetParams`.

        Records the loop's state and action names (a simulator's object state too) and one video
        per camera at the tick rate. A free-running loop (a simulation) waits for its encoders
        rather than repeat frames. Opens nothing: the dataset folder is opened (created, or
        checked and resumed) by :meth:`start`. Errors name ``context.option`` (``--dataset-out``)
        when the entry stands for one.

        Raises:
            ROSConfigError: A wrong parameter (named with the allowed keys); a tick rate that is not
                a whole number (a dataset's fps is); a camera id that cannot name a video folder.
        """
        config = validate_model(LeRobotDatasetParams, dict(params), field_prefix="observers[].params")
        if not math.isclose(context.rate_hz, round(context.rate_hz)):
            raise ROSConfigError(
                f"a dataset records whole frames per second; the tick rate is {context.rate_hz:g} Hz",
                field=context.option or "rate_hz",
                hint="use a whole number of Hz to record",
            )
        field = context.option or _ROOT_FIELD
        sink = LeRobotDatasetSink(
            resolve_user_path(config.root, context.base_dir, field=field),
            fps=round(context.rate_hz),
            robot_type=context.robot_id,
            joint_names=context.joint_names,
            action_names=context.action_names,
            environment_state_names=context.environment_state_names,
            cameras=[schema.CameraSpec(c.id, c.width, c.height) for c in context.cameras],
            vcodec=config.vcodec,
            overflow=OverflowPolicy.WAIT if context.free_running else OverflowPolicy.REPEAT,
            resume=config.resume,
            field=field,
            defer_open=True,
            takeover=context.takeover,
        )
        return cls(
            sink,
            joint_names=context.joint_names,
            episode_every_s=config.episode_every_s,
            highlight_s=config.highlight_s,
        )

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
                lambda: self._ends_done >= self._ends_queued or self.failure is not None, _wait_s(timeout_s)
            )

    def save_highlight(self) -> Future[EpisodeSummary | None]:
        """Commit what the highlight ring holds now as one episode, with the episode's task. Any thread.

        Returns at once; the rows are written on the highlight-saving thread while the ring goes on
        filling. Ticks handed to the recorder in the last few milliseconds that its worker has not
        taken yet are not part of the highlight.

        Returns:
            A future of the committed episode's summary; of ``None`` (and a warning) when nothing
            was saved: the ring is empty (no episode open, or none of its ticks reached the worker
            yet), recording has stopped, the recorder is closed, or :data:`MAX_PENDING_SAVES` saves
            are still waiting. A write failure stops recording, as any other does, and is the
            future's exception.

        Raises:
            ROSRuntimeError: The recorder was not built with ``highlight_s``.
        """
        ring, saver = self.highlight, self._saver
        if ring is None or saver is None:
            raise ROSRuntimeError("this recorder holds no highlights: build it with highlight_s to save them")
        done: Future[EpisodeSummary | None] = Future()
        highlight = ring.snapshot()
        why = None
        if self.failure is not None:
            why = "recording has stopped"
        elif highlight is None:
            why = "nothing is held: no episode is open, or none of its ticks has reached the recorder yet"
        else:
            with self._ends:
                if self._saves_pending >= MAX_PENDING_SAVES:
                    why = f"{MAX_PENDING_SAVES} highlights are still being saved"
                else:
                    self._saves_pending += 1
        if why is None and highlight is not None:
            try:
                return saver.submit(self._save, highlight)
            except RuntimeError:  # shut down: the recorder is closed
                why = "the recorder is closed"
                with self._ends:
                    self._saves_pending -= 1
        _log.warning("highlight not saved", dataset=str(self.sink.root), reason=why)
        done.set_result(None)
        return done

    @property
    def repeated_frames(self) -> int:
        """Frames repeated in videos because an encoder fell behind, over every episode so far."""
        return sum(sum(e.repeated_frames.values()) for e in self.episodes)

    def report(self) -> dict[str, int]:
        """What the recording has done so far (the worker may still be writing the last ticks).

        In highlight mode it also says what the ring holds: ``highlight_rows`` of at most
        ``highlight_capacity_rows``, in ``highlight_bytes`` (JPEG frames and an estimate of the rows).
        """
        committed = [e for e in self.episodes if e.committed]
        out = {
            "episodes_committed": len(committed),
            "episodes_discarded": len(self.episodes) - len(committed),
            "frames": sum(e.frames for e in committed),
            "repeated_frames": self.repeated_frames,
            "dropped_ticks": self.dropped_ticks,
            "errors": self.errors,
        }
        if self.highlight is not None:
            out["highlight_capacity_rows"] = self.highlight.capacity_rows
            out["highlight_rows"] = self.highlight.rows
            out["highlight_bytes"] = self.highlight.nbytes
        return out

    # -- worker ----------------------------------------------------------------------------

    def on_overflow(self, tick: TickResult) -> None:
        if tick.step_idx is not None:
            self.dropped_ticks += 1
            metrics.add(semconv.METRIC_RECORDING_DROPPED_TICKS)

    def handle_episode_start(self, episode_idx: int, task: str) -> None:
        if self.failure is not None:
            return
        self._held = None
        self._task = task
        if self.highlight is not None:
            self.highlight.start(task)
            return
        self._begin_part()

    def _begin_part(self) -> None:
        """Open the next dataset episode for the runner's episode (its first part, or the next one)."""
        assert self._task is not None
        try:
            dataset_idx = self.sink.begin_episode(self._task)
        except Exception as exc:
            self._fail(exc)
            return
        self._part_filled = 0
        self._announce = (dataset_idx, self._task)  # logged with its first row: the episode is being recorded then

    def handle_episode_end(self, episode_idx: int, *, success: bool, keep: bool) -> None:
        self._task = None
        try:
            if self.highlight is not None:
                self.highlight.stop()  # only what was saved is kept
            elif self.sink.episode_open:
                self._end_episode(success=success, keep=keep and self.failure is None)
        except Exception as exc:
            self._fail(exc)
        finally:
            with self._ends:
                self._ends_done += 1
                self._ends.notify_all()

    def _end_episode(self, *, success: bool | None, keep: bool) -> None:
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
        if self.failure is not None or self._task is None or tick.step_idx is None:
            return  # stopped, or between episodes (a simulator's reset tick included)
        try:
            built = self._row(tick, world)
            if built is None:
                return  # nothing measured yet: no row can say where the robot was
            row, frames = built
            if self.highlight is not None:
                self.highlight.push(row, frames)
            else:
                self._write_row(row, frames)
        except Exception as exc:
            self._fail(exc)
            try:
                if self.sink.episode_open and self.highlight is None:
                    self.sink.end_episode(keep=False)  # the episode under way is lost; the committed ones stay
            except Exception as discard_exc:
                _log.debug("discarding the episode under way failed", exc_info=discard_exc)

    def _write_row(self, row: dict[str, Any], frames: dict[str, SensorFrame]) -> None:
        """Add one row to the dataset episode under way, after committing it if it is a full part.

        A full part is committed when the next row comes (one tick later), not at once: if the
        runner's episode ends there instead, its ``episode_end`` commits the part with its outcome.
        """
        if self.part_rows is not None and self._part_filled >= self.part_rows:
            self._end_episode(success=None, keep=True)  # a part's outcome is not known: the episode goes on
            self._begin_part()
            if self.failure is not None:
                return
        self.sink.add_row(row, frames)
        self._part_filled += 1
        if self._announce is not None:
            _log.info("recording episode", episode=self._announce[0], task=self._announce[1])
            self._announce = None
        metrics.add(semconv.METRIC_RECORDING_FRAMES)
        for cam in self.sink.cameras:
            if row.get(schema.camera_column(cam.sensor_id, "repeated")):
                metrics.add(semconv.METRIC_RECORDING_REPEATED_FRAMES, 1, {semconv.ATTR_SENSOR_ID: cam.sensor_id})

    def _row(self, tick: TickResult, world: WorldState | None) -> tuple[dict[str, Any], dict[str, SensorFrame]] | None:
        """The tick's dataset row and its cameras' frames; ``None`` before any joint state was measured."""
        state = self._measured_state(world)
        if state is None:
            return None
        if tick.action_applied and tick.sent_action is not None:
            self._held = list(tick.sent_action)
        action = self._held if self._held is not None else self._hold_default(state)
        trace_id, span_id = _ids(tick.trace_context)
        mirrored = tick.model_dump(mode="json", include=self._mirrored)
        row: dict[str, Any] = {schema.STATE: state, schema.ACTION: action}
        for tick_column in self._tick_columns:
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
        return row, frames

    def handle_close(self) -> None:
        if self._saver is not None:
            self._saver.shutdown(wait=True)  # the highlights asked for are written before the dataset closes
        if self.highlight is not None:
            self.highlight.close()
        if self.sink.episode_open:
            # The run ended inside an episode (a stop, a fault): what was recorded is kept.
            self.handle_episode_end(-1, success=False, keep=True)
        self.sink.close()

    # -- highlight-saving thread ---------------------------------------------------------------

    def _save(self, highlight: Highlight) -> EpisodeSummary | None:
        """Write ``highlight`` as one episode with the sink (only this thread uses it in highlight mode).

        Raises:
            ROSRuntimeError: Writing failed: recording stops (:attr:`failure`).
        """
        try:
            if self.failure is not None:
                _log.warning("highlight not saved", dataset=str(self.sink.root), reason="recording has stopped")
                return None
            return self._write_highlight(highlight)
        except Exception as exc:
            self._fail(exc)
            try:
                if self.sink.episode_open:
                    self.sink.end_episode(keep=False)
            except Exception as discard_exc:
                _log.debug("discarding the highlight under way failed", exc_info=discard_exc)
            raise self.failure or ROSRuntimeError(str(exc)) from exc
        finally:
            with self._ends:
                self._saves_pending -= 1

    def _write_highlight(self, highlight: Highlight) -> EpisodeSummary:
        """Write ``highlight``'s rows, emptying it as they go, and commit them."""
        ring = self.highlight
        assert ring is not None
        self.sink.begin_episode(highlight.task)
        rows = highlight.rows
        count = len(rows)
        rows.reverse()
        while rows:  # consumed as written: a row the ring has dropped meanwhile is freed once it is written
            held = rows.pop()
            frames = {sensor_id: frame.restore() for sensor_id, frame in held.frames.items()}
            self.sink.add_row(dict(held.row), frames)  # a copy: the sink adds its columns to the row it gets
        metrics.add(semconv.METRIC_RECORDING_FRAMES, count)
        self._end_episode(success=None, keep=True)
        summary = self.episodes[-1]
        _log.info(
            "highlight saved",
            episode=summary.episode_idx,
            frames=summary.frames,
            seconds=round(summary.frames / self.sink.fps, 3),
            ring_rows=ring.rows,
            ring_bytes=ring.nbytes,
        )
        return summary

    # -- any recording thread ------------------------------------------------------------------

    def _fail(self, exc: Exception) -> None:
        """Stop recording at the first failure: one line in the log, the traceback at debug level."""
        root = str(self.sink.root)
        with self._ends:
            self.errors += 1
            if self.failure is not None:
                return
            text = str(exc) if root in str(exc) else f"recording into {root} failed: {exc}"
            self.failure = ROSRuntimeError(text)
            self._ends.notify_all()
        _log.error("recording stopped", dataset=root, error=text)
        _log.debug("recording stopped", exc_info=exc)
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


def _rows(seconds: float | None, fps: int, field: str, *, maximum: float | None = None) -> int | None:
    """``seconds`` of rows at ``fps`` (``None`` stays ``None``).

    Raises:
        ROSConfigError: Not a positive, finite number, more than ``maximum``, or shorter than one frame.
    """
    if seconds is None:
        return None
    if not (math.isfinite(seconds) and seconds > 0):
        raise ROSConfigError(f"must be a positive, finite number of seconds, got {seconds}", field=field)
    if maximum is not None and seconds > maximum:
        raise ROSConfigError(f"must be at most {maximum:g} s (it is held in memory), got {seconds:g}", field=field)
    rows = round(seconds * fps)
    if rows < 1:
        raise ROSConfigError(f"{seconds:g} s is shorter than one frame at {fps} fps", field=field)
    return rows


def _wait_s(seconds: float) -> float:
    """``seconds`` as a thread wait takes it: at most ``threading.TIMEOUT_MAX`` (a longer one raises)."""
    return min(seconds, threading.TIMEOUT_MAX)


def _ids(traceparent: str | None) -> tuple[str | None, str | None]:
    """Trace and span id from a W3C ``traceparent`` value (``None`` when the tick was not traced)."""
    if not traceparent:
        return None, None
    parts = traceparent.split("-")
    if len(parts) != 4:
        return None, None
    return parts[1], parts[2]
