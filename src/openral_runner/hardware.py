"""``HardwareRunner``: sensors → world state → skill → safety → HAL, once per tick, on a robot.

The tick body is :class:`~openral_runner.skill_runner.SkillRunnerBase`'s; this runner says what
sensing and acting mean on a robot: each sensor reader's latest frame and the HAL's state, the
aggregator's snapshot, ``HAL.send_action``. It also owns what only a robot has: opening and
closing the HAL and the readers, waiting for fresh sensors before the first tick, the e-stop.

Stale required sensors and failed state reads withhold the tick's action, as the base's phases do
for a skill's exception or a safety violation, so the robot is never driven by an action computed
from bad inputs; the HAL keeps holding its last accepted target.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import Any

import structlog

from openral_core import (
    Action,
    JointState,
    RealtimeConfig,
    ROSConfigError,
    ROSError,
    ROSPerceptionStale,
    ROSRuntimeError,
    ROSSyncError,
    RunResult,
    SensorFrame,
    StopReason,
    SyncConfig,
    WithheldReason,
    WorldState,
)
from openral_core.environment import DEFAULT_SENSOR_READY_TIMEOUT_S
from openral_hal.protocol import HAL
from openral_observability import metrics, record_error, semconv, tracer
from openral_observability.observer import StartableObserver, ThumbnailSource, TickObserver
from openral_rskill.base import RSkillBase
from openral_runner.realtime import apply_realtime
from openral_runner.safety import SafetyClient, SafetyCommitListener, SafetyStateObserver
from openral_runner.sensor_lag import ReportingReader, SensorReads
from openral_runner.sensor_reader import SensorReader, read_synced_set, with_read_synced
from openral_runner.skill_runner import SkillRunnerBase
from openral_runner.thumbnails import ThumbnailPublisher
from openral_runner.tick_context import TickContext
from openral_world_state import WorldStateAggregator

_log = structlog.get_logger(__name__)

_DEFAULT_THUMBNAIL_HZ = 25.0
"""Thumbnails per second of a runner built in code without ``observers`` (its ``thumbnail_hz`` default)."""

_PHASE_MARGIN_S = 0.002
"""Slack between a camera frame's arrival and the tick that reads it, for capture-thread jitter."""


class HardwareRunner(SkillRunnerBase):
    """Closes the loop on a robot (or its twin).

    The caller configures and activates the skill; the runner opens and closes the HAL and
    the sensor readers. ``activate()`` rolls back whatever it opened if any step fails.

    Args:
        hal: The robot.
        skill: An active skill.
        aggregator: Builds the world state each tick.
        sensor_readers: Capture backends, opened in order at activation.
        safety_client: Checks every action; defaults to ``NullSafetyClient``. Its optional
            ``observe_state`` and ``commit`` are called each tick when it has them.
        task: Instruction placed in every world state.
        realtime: Real-time knobs applied to the calling thread at activation.
        sync: Cameras read as one set with bounded capture skew each tick.
        observers: What watches the ticks, as built from a deployment's ``observers:`` entries
            (:func:`~openral_runner.composition.build_observers`); started at activation and
            closed with the runner.
        thumbnail_hz: Shorthand for a ``thumbnails`` observer added after ``observers``: small JPEG
            thumbnails of each camera at this rate for the dashboard span and every thumbnail
            subscriber; 0 (or no camera) adds none. Default: 25 Hz for a runner given no
            ``observers``, none for one given them (its entries say whether it has thumbnails).
        recorder: Shorthand for an observer that records episodes (a ``RolloutRecorder``), added
            as the first observer.
        sensor_ready_timeout_s: How long a run waits, before its first tick, for every required
            sensor to deliver a frame within its ``max_age_ms``.
        **base_kwargs: ``InferenceRunnerBase`` options (rate, policy, clock, ...).
    """

    def __init__(
        self,
        *,
        hal: HAL,
        skill: RSkillBase,
        aggregator: WorldStateAggregator,
        sensor_readers: Sequence[SensorReader] = (),
        safety_client: SafetyClient | None = None,
        task: str | None = None,
        realtime: RealtimeConfig | None = None,
        sync: SyncConfig | None = None,
        observers: Sequence[TickObserver] | None = None,
        thumbnail_hz: float | None = None,
        recorder: TickObserver | None = None,
        sensor_ready_timeout_s: float = DEFAULT_SENSOR_READY_TIMEOUT_S,
        **base_kwargs: Any,
    ) -> None:
        base_kwargs.setdefault("runner_name", "hardware_runner")
        super().__init__(skill=skill, safety_client=safety_client, task=task, **base_kwargs)
        self.hal = hal
        self.aggregator = aggregator
        self.sensor_readers = list(sensor_readers)
        self.realtime = realtime
        self.sync = sync
        if not (math.isfinite(sensor_ready_timeout_s) and sensor_ready_timeout_s > 0):
            raise ROSConfigError(
                f"must be a finite number > 0, got {sensor_ready_timeout_s}", field="faults.sensor_ready_timeout_s"
            )
        self.sensor_ready_timeout_s = sensor_ready_timeout_s
        self._reads = {r.sensor_id: SensorReads() for r in self.sensor_readers}
        if thumbnail_hz is None:
            thumbnail_hz = _DEFAULT_THUMBNAIL_HZ if observers is None else 0.0
        if not (math.isfinite(thumbnail_hz) and thumbnail_hz >= 0):
            raise ROSConfigError(f"must be a finite number >= 0, got {thumbnail_hz}", field="thumbnail_hz")
        self.observers.extend(([] if recorder is None else [recorder]) + list(observers or ()))
        if self.sensor_readers and thumbnail_hz > 0:
            self.observers.append(ThumbnailPublisher(thumbnail_hz))
        synced = set(sync.sensors) if sync is not None else set()
        clock_ns = self._clock.now_ns
        self._synced_readers = [
            with_read_synced(r, clock_ns=clock_ns) for r in self.sensor_readers if r.sensor_id in synced
        ]
        # Each free reader with its read counters, paired once: the tick looks nothing up.
        self._free_readers = [(r, self._reads[r.sensor_id]) for r in self.sensor_readers if r.sensor_id not in synced]
        self._required_ids = frozenset(r.sensor_id for r in self.sensor_readers if aggregator.is_required(r.sensor_id))
        self._opened: ExitStack | None = None
        self._episode_idx = -1
        self._episode_open = False
        self._episode_start_tick = 0
        self._hal_attrs = {
            semconv.ATTR_HAL_ADAPTER: type(hal).__name__.lower(),
            semconv.ATTR_HAL_ROBOT_MODEL: hal.robot_id,
        }
        self._sensor_attrs = {r.sensor_id: {semconv.ATTR_SENSOR_ID: r.sensor_id} for r in self.sensor_readers}
        self._component_attrs = {name: {semconv.ATTR_COMPONENT: name} for name in aggregator.components}
        # What the readers gave this runner: each sensor's latest frame (held, so a stale sensor's
        # last frame still reaches the skill) and this tick's failed reads, their verdicts.
        self._frames: dict[str, SensorFrame] = {}
        self._failures: dict[str, ROSError] = {}

    def activate(self) -> None:
        """Start the observers, connect the HAL, then open every reader; on any failure close what was opened.

        Observers start first, so a dataset folder or a port that cannot be used is refused before
        the robot is touched.

        A stop requested while starting (a signal, another thread) is honoured between steps:
        whatever was opened is closed again, the HAL disconnected included.

        Raises:
            ROSStopRequested: A stop was requested during start-up; everything was rolled back.
            ROSError: Whatever the failing component raised, after rollback.
        """
        if self._opened is not None:
            super().activate()
            return
        with ExitStack() as stack:
            self._check_stop()
            # Closed in reverse: thumbnail makers (producers) first, so their last thumbnails still
            # reach the observers that subscribe to them.
            for observer in sorted(self.observers, key=lambda o: isinstance(o, ThumbnailSource)):
                stack.callback(self._safe_close, f"observer {type(observer).__name__}", observer.close)
            for observer in self.observers:
                if isinstance(observer, StartableObserver):
                    observer.start()  # idempotent: the base's activation finds it started
            self._check_stop()
            self.hal.connect()
            stack.callback(self._safe_close, "hal", self.hal.disconnect)
            for reader in self.sensor_readers:
                self._check_stop()
                reader.open()
                stack.callback(self._safe_close, f"sensor {reader.sensor_id}", reader.close)
            self._check_stop()
            super().activate()  # starts the telemetry worker thread
            stack.callback(super().deactivate)
            if self.realtime is not None:
                # Last, so the capture, physics and telemetry threads started above keep ordinary priority.
                settings = apply_realtime(self.realtime)
                self.metadata["realtime"] = settings.report
                stack.callback(settings.restore)
            self._opened = stack.pop_all()

    def deactivate(self) -> None:
        """Close every reader, then disconnect the HAL. Idempotent; failures are logged, not raised."""
        super().deactivate()
        opened, self._opened = self._opened, None
        if opened is not None:
            opened.close()

    @staticmethod
    def _safe_close(what: str, close: Callable[[], None]) -> None:
        try:
            close()
        except Exception as exc:  # a failing close must not stop the others from closing
            _log.warning("close failed", component=what, error=str(exc))

    @property
    def safety_client(self) -> SafetyClient:
        """The client every action passes; assigning one decides once which of its optional hooks run."""
        return self._safety_client

    @safety_client.setter
    def safety_client(self, client: SafetyClient) -> None:
        self._safety_client = client
        self._observe_state: Callable[[JointState], None] | None = (
            client.observe_state if isinstance(client, SafetyStateObserver) else None
        )
        self._commit_sent: Callable[[Action], None] | None = (
            client.commit if isinstance(client, SafetyCommitListener) else None
        )

    # -- schedule phase --------------------------------------------------------------------

    def _schedule_origin(self) -> float:
        """Wait until every required sensor is fresh, then start the schedule just after a frame of the first.

        Raises:
            ROSRuntimeError: A required sensor delivered no frame within its ``max_age_ms`` in
                ``sensor_ready_timeout_s`` (the message names it, its newest frame's age and its capture
                rate), or failed while starting (its own error).
        """
        for reads in self._reads.values():
            reads.clear()
        self._await_fresh_sensors()
        return self._phase_origin()

    def _await_fresh_sensors(self) -> None:
        """Block (bounded) until each required sensor's newest frame is within its own age limit.

        A camera that delivered its first frame when it opened may have delivered none since
        (a software renderer on a busy machine, a camera still adjusting its exposure): starting
        the loop then would withhold its first ticks for stale frames, and five of those stop it.
        """
        clock_ns = self._clock.now_ns
        deadline_ns = clock_ns() + int(self.sensor_ready_timeout_s * 1e9)
        # Bounded on the wall clock too, so a clock that does not advance by itself cannot hang it.
        give_up = time.monotonic() + self.sensor_ready_timeout_s
        for reader in self.sensor_readers:
            if reader.sensor_id not in self._required_ids:
                continue
            synced = with_read_synced(reader, clock_ns=clock_ns)
            while True:
                try:
                    reader.read_latest()
                    break
                except ROSPerceptionStale as exc:
                    if clock_ns() >= deadline_ns or time.monotonic() >= give_up:
                        raise self._not_ready(reader, exc) from exc
                    newest = self._newest_stamp_ns(reader)
                with contextlib.suppress(ROSPerceptionStale):  # at the deadline: judged by the next read
                    synced.read_synced(deadline_ns, newer_than_ns=newest)

    @staticmethod
    def _newest_stamp_ns(reader: SensorReader) -> int:
        try:
            return reader.read_latest(math.inf).stamp_ns
        except ROSPerceptionStale:
            return 0

    def _not_ready(self, reader: SensorReader, stale: ROSPerceptionStale) -> ROSRuntimeError:
        """The start-up failure for ``reader``: its newest frame's age against its limit, and its capture figures."""
        if stale.age_ms is None:
            what = "delivered no frame"
        else:
            what = f"delivered no frame younger than {stale.max_age_ms:g} ms (its newest was {stale.age_ms:.0f} ms old)"
        figures = reader.report() if isinstance(reader, ReportingReader) else {}
        capture = ""
        if figures.get("delivered_fps") is not None and figures.get("requested_fps") is not None:
            capture = f"; it delivers {figures['delivered_fps']:.1f} of {figures['requested_fps']:g} fps"
            if figures.get("render_ms"):
                capture += f" at {figures['render_ms']:.0f} ms per render"
        advice = figures.get("advice") or "lower its fps or image size, or check the device"
        return ROSRuntimeError(
            f"sensor '{reader.sensor_id}' {what} within {self.sensor_ready_timeout_s:g} s of start{capture}. "
            f"To fix: {advice}; or raise its max_age_ms or faults.sensor_ready_timeout_s"
        )

    def _phase_origin(self) -> float:
        """Start the schedule just after a frame of the first required camera arrives.

        A camera and a tick at the same rate lock their phases; started at a random instant the
        tick would often read each frame almost a full period old. Starting slot 0 right after a
        capture (plus a small margin for publish jitter) keeps the frames the skill sees fresh.
        Without a camera, or if none delivers within two periods, the schedule starts now.
        """
        now = self._clock.now()
        first = next((r for r in self.sensor_readers if r.sensor_id in self._required_ids), None)
        if first is None:
            return now
        reader = with_read_synced(first, clock_ns=self._clock.now_ns)
        try:
            latest = reader.read_latest(float("inf")).stamp_ns
            wait_ns = int(2 * self.period_s * 1e9)
            reader.read_synced(self._clock.now_ns() + wait_ns, newer_than_ns=latest)
        except ROSError:
            return self._clock.now()
        return self._clock.now() + min(_PHASE_MARGIN_S, self.period_s / 4)

    # -- episodes ------------------------------------------------------------------------

    def episode_start(self, task_string: str) -> int:
        """Begin an episode: the skill is reset, ``task_string`` becomes the task, observers are told.

        Returns:
            The new episode's index (0 for the first).

        Raises:
            ROSRuntimeError: An episode is already open.
        """
        if self._episode_open:
            raise ROSRuntimeError(f"episode {self._episode_idx} is still open: call episode_end() first")
        self._episode_idx += 1
        self._episode_open = True
        self._episode_start_tick = self._tick_idx
        self.task = task_string or None
        self._reset_skill()
        self.metadata.setdefault("episodes", []).append(
            {"episode_idx": self._episode_idx, "task": task_string, "start_tick": self._tick_idx}
        )
        self._tell_episode_start(self._episode_idx, task_string)
        return self._episode_idx

    def episode_end(self, *, success: bool, keep: bool = True) -> None:
        """Close the open episode, record its outcome and tell the observers.

        Args:
            success: Whether the episode reached its goal.
            keep: ``False`` throws the episode away (a recorder discards the take).

        Raises:
            ROSRuntimeError: No episode is open.
        """
        if not self._episode_open:
            raise ROSRuntimeError("no episode is open: call episode_start() first")
        self._episode_open = False
        self.metadata["episodes"][-1].update(success=success, kept=keep, end_tick=self._tick_idx)
        self._tell_episode_end(self._episode_idx, success=success, keep=keep)

    # -- the tick's hooks --------------------------------------------------------------------

    def _sense(self, tick: TickContext) -> None:
        """Each reader's latest frame (or its verdict), the synchronised set, then the HAL's state."""
        if self._episode_open:
            tick.episode_idx = self._episode_idx
            tick.step_idx = tick.tick_idx - self._episode_start_tick
        self._failures.clear()
        for reader, reads in self._free_readers:
            self._read_sensor(reader, reads)
        if self._synced_readers:
            self._read_synced_set()
        telemetry = self._telemetry
        started = self._clock.now()
        span = telemetry.start_span(semconv.SPAN_HAL_READ_STATE, attributes=self._hal_attrs)
        try:
            state = self.hal.read_state()
            self.aggregator.update_joint_state(state)
            if self._observe_state is not None:
                self._observe_state(state)
        except ROSError as exc:
            tick.withhold(WithheldReason.READ_STATE)
            record_error(span, exc)
            _log.warning("read_state failed", error=str(exc), tick=tick.tick_idx)
        finally:
            span.end()
        # A duration on the runner's clock is never negative: recorded as is, without ``record_ms``'s check.
        telemetry.record(semconv.METRIC_HAL_READ_STATE_DURATION, (self._clock.now() - started) * 1e3, self._hal_attrs)

    def _world_state(self, tick: TickContext) -> WorldState:
        """The aggregator's snapshot: the one verdict on every component, built from the readers' own verdicts."""
        telemetry = self._telemetry
        span = telemetry.start_span(semconv.SPAN_WORLD_STATE_SNAPSHOT)
        try:
            world = self.aggregator.snapshot(self._frames, failures=self._failures, task=self.task, span=span)
        finally:
            span.end()
        for name, diagnosis in world.diagnostics.items():
            if diagnosis.age_ms is not None:
                telemetry.record_ms(semconv.METRIC_WORLD_STATE_STALENESS, diagnosis.age_ms, self._component_attrs[name])
        if self.sensor_readers:
            diagnostics = world.diagnostics
            tick.stale_sensors.extend(r.sensor_id for r in self.sensor_readers if diagnostics[r.sensor_id].stale)
        if world.stale_required:
            tick.withhold(WithheldReason.STALE_SENSOR)
        return world

    def _actuate(self, tick: TickContext, action: Action | None) -> WithheldReason | None:
        """Send ``action`` to the HAL; a withheld one sends nothing (the HAL keeps holding its last target)."""
        if action is None:
            return None
        telemetry = self._telemetry
        started = self._clock.now()
        failed: WithheldReason | None = None
        span = telemetry.start_span(semconv.SPAN_HAL_SEND_ACTION, attributes=self._hal_attrs)
        try:
            self.hal.send_action(action)
            if self._commit_sent is not None:
                self._commit_sent(action)
        except ROSError as exc:
            failed = WithheldReason.HAL_ERROR
            record_error(span, exc)
            _log.warning("send_action failed", error=str(exc), tick=tick.tick_idx)
        finally:
            span.end()
        telemetry.record(semconv.METRIC_HAL_SEND_ACTION_DURATION, (self._clock.now() - started) * 1e3, self._hal_attrs)
        return failed

    def _read_synced_set(self) -> None:
        """Read the synchronised cameras as one set; without a set within the skew, each is marked stale."""
        assert self.sync is not None
        span = self._telemetry.start_span(semconv.SPAN_SENSORS_READ_SYNCED)
        try:
            remaining_s = max(0.0, self._tick.deadline_s - self._clock.now())
            timeout_s = min(self.sync.timeout_ms / 1e3, remaining_s)
            frames = read_synced_set(
                self._synced_readers,
                max_skew_ms=self.sync.max_skew_ms,
                deadline_ns=self._clock.now_ns() + int(timeout_s * 1e9),
                clock_ns=self._clock.now_ns,
            )
        except ROSError as exc:
            attrs: dict[str, Any] = {semconv.ATTR_EXCEPTION_MESSAGE: str(exc)}
            if isinstance(exc, ROSSyncError):
                attrs[semconv.ATTR_SYNC_SKEW_MS] = exc.skew_ms
            span.add_event(semconv.EVENT_SENSOR_SYNC_FAILED, attrs)
            for reader in self._synced_readers:
                self._reads[reader.sensor_id].reads += 1
                self._reads[reader.sensor_id].stale_read(None, None)
                self._failures[reader.sensor_id] = ROSPerceptionStale(reader.sensor_id, age_ms=None, max_age_ms=None)
                metrics.add(semconv.METRIC_SENSORS_STALE_READS, 1, {semconv.ATTR_SENSOR_ID: reader.sensor_id})
        else:
            stamps = [frame.stamp_ns for frame in frames.values()]
            if span.is_recording():
                span.set_attribute(semconv.ATTR_SYNC_SKEW_MS, (max(stamps) - min(stamps)) / 1e6)
            now_ns = self._clock.now_ns()
            for frame in frames.values():
                self._reads[frame.sensor_id].reads += 1
                self._accept_frame(frame)
                self._telemetry.record_ms(
                    semconv.METRIC_SENSORS_AGE, frame.age_ms(now_ns), self._sensor_attrs[frame.sensor_id]
                )
        finally:
            span.end()

    def _build_run_result(self, n_ticks: int, stop_reason: StopReason) -> RunResult:
        """The base's result, with each sensor's reads, stale reads and capture report in ``metadata["sensors"]``."""
        if self.sensor_readers:
            self.metadata["sensors"] = {
                r.sensor_id: {
                    **(r.report() if isinstance(r, ReportingReader) else {}),
                    **self._reads[r.sensor_id].summary(),
                }
                for r in self.sensor_readers
            }
        return super()._build_run_result(n_ticks, stop_reason)

    def _accept_frame(self, frame: SensorFrame) -> None:
        self._frames[frame.sensor_id] = frame

    def _read_sensor(self, reader: SensorReader, reads: SensorReads) -> None:
        """Take one reader's latest frame, or its verdict (stale, failed) on this tick's read, for the snapshot."""
        span = self._telemetry.start_span(semconv.SPAN_SENSORS_READ)
        reads.reads += 1
        try:
            frame = reader.read_latest()
        except ROSPerceptionStale as exc:
            self._failures[reader.sensor_id] = exc
            reads.stale_read(exc.age_ms, exc.max_age_ms)
            self._on_stale(span, exc)
        except ROSError as exc:
            self._failures[reader.sensor_id] = exc
            record_error(span, exc)
        else:
            self._accept_frame(frame)
            age_ms = frame.age_ms(self._clock.now_ns())
            self._telemetry.record_ms(semconv.METRIC_SENSORS_AGE, age_ms, self._sensor_attrs[reader.sensor_id])
            if span.is_recording():
                span.set_attributes({semconv.ATTR_SENSOR_ID: reader.sensor_id, semconv.ATTR_SENSOR_AGE_MS: age_ms})
        finally:
            span.end()

    # -- fault handling ------------------------------------------------------------------

    def _on_stale(self, span: Any, exc: ROSPerceptionStale) -> None:
        attrs: dict[str, Any] = {semconv.ATTR_SENSOR_ID: exc.sensor_id}
        if exc.age_ms is not None:
            attrs[semconv.ATTR_SENSOR_AGE_MS] = exc.age_ms
        span.add_event(semconv.EVENT_SENSOR_STALE, attrs)
        metrics.add(semconv.METRIC_SENSORS_STALE_READS, 1, {semconv.ATTR_SENSOR_ID: exc.sensor_id})

    def _estop_robot(self) -> None:
        estop_span = tracer().start_span(semconv.SPAN_HAL_ESTOP, attributes=self._hal_attrs)
        try:
            self.hal.estop()
        except Exception as estop_exc:  # still stop the loop even if the HAL cannot confirm
            record_error(estop_span, estop_exc)
            _log.error("HAL estop failed", error=str(estop_exc))
        finally:
            estop_span.end()
