"""Every span, attribute, event and metric name openral emits, in one table.

The names the spec gives (``rskill.*``, ``skill.*``, ``safety.*``) are kept as it gives them;
every other name is ``openral.<layer>.*``. Durations are histograms in milliseconds; counters
count events. A tick attribute is declared on the ``TickResult`` field it renders (its
``SpanAttribute``); :data:`TICK_ATTRIBUTES` and the ``ATTR_*`` constants of tick fields are read
off those declarations.

The span tree of one tick::

    cli.command                      (one per ``openral`` invocation; the root under the CLI)
    └── rskill.tick                  (one per tick; per-phase ``skill.*_ms`` attributes)
        ├── sensors.read_latest      (one per free-running camera) / sensors.read_synced
        ├── hal.read_state
        ├── world_state.snapshot
        ├── skill.chunk_inference    (current while the skill runs: spans it opens nest here)
        ├── safety.check
        └── hal.send_action          (or hal.estop)
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Final

from openral_core.results import SpanAttribute, tick_fields_with

TRACER_NAME: Final = "openral"
METER_NAME: Final = "openral"

# Spans
SPAN_CLI_COMMAND: Final = "cli.command"
SPAN_TICK: Final = "rskill.tick"
SPAN_SENSORS_READ: Final = "sensors.read_latest"
SPAN_HAL_READ_STATE: Final = "hal.read_state"
SPAN_WORLD_STATE_SNAPSHOT: Final = "world_state.snapshot"
SPAN_SKILL_INFERENCE: Final = "skill.chunk_inference"
SPAN_SKILL_EXECUTE: Final = "rskill.execute"
"""The spec's name for a skill's execution; the runner emits :data:`SPAN_SKILL_INFERENCE` for it."""
SPAN_SAFETY_CHECK: Final = "safety.check"
SPAN_HAL_SEND_ACTION: Final = "hal.send_action"
SPAN_HAL_ESTOP: Final = "hal.estop"
SPAN_SENSORS_THUMBNAIL: Final = "sensors.thumbnail"
SPAN_SENSORS_READ_SYNCED: Final = "sensors.read_synced"

# Tick attributes
TICK_ATTRIBUTES: Final[Mapping[str, str]] = MappingProxyType(
    {name: attribute.name for name, attribute in tick_fields_with(SpanAttribute).items()}
)
"""``TickResult`` field → its ``rskill.tick`` span attribute, read off the field's :class:`SpanAttribute`.

A field without one stays off the span (``start_ns`` and ``trace_context`` are the span's own
start and context; the actions, stale sensors and the deadline flag are carried by the safety and
sensor spans and by the lateness attribute). How a value is rendered follows from the field's type
(:mod:`openral_runner.tick_span`): a list as its length, an optional field only when set.
"""
ATTR_TICK_IDX: Final = TICK_ATTRIBUTES["tick_idx"]
ATTR_TICK_MS: Final = TICK_ATTRIBUTES["tick_ms"]
ATTR_SENSORS_MS: Final = TICK_ATTRIBUTES["sensors_ms"]
ATTR_WORLD_STATE_MS: Final = TICK_ATTRIBUTES["world_state_ms"]
ATTR_INFERENCE_MS: Final = TICK_ATTRIBUTES["inference_ms"]
ATTR_SAFETY_MS: Final = TICK_ATTRIBUTES["safety_ms"]
ATTR_HAL_MS: Final = TICK_ATTRIBUTES["hal_ms"]
ATTR_ACTION_APPLIED: Final = TICK_ATTRIBUTES["action_applied"]
ATTR_WITHHELD_REASON: Final = TICK_ATTRIBUTES["withheld_reason"]
ATTR_SAFETY_VIOLATIONS: Final = TICK_ATTRIBUTES["safety_violations"]
ATTR_LATENESS_MS: Final = TICK_ATTRIBUTES["lateness_ms"]
ATTR_STEP_IDX: Final = TICK_ATTRIBUTES["step_idx"]
ATTR_EPISODE_IDX: Final = TICK_ATTRIBUTES["episode_idx"]
ATTR_REWARD: Final = TICK_ATTRIBUTES["reward"]
ATTR_TERMINATED: Final = TICK_ATTRIBUTES["terminated"]
ATTR_TRUNCATED: Final = TICK_ATTRIBUTES["truncated"]
ATTR_TAKEOVER_INTERVENTION: Final = TICK_ATTRIBUTES["intervention"]
ATTR_TAKEOVER_ACTIVE_SKILL: Final = TICK_ATTRIBUTES["active_skill"]
ATTR_TAKEOVER_RAMP: Final = TICK_ATTRIBUTES["handover_ramp"]
ATTR_SKILL_ID: Final = "skill.id"
"""The skill (or runner) a tick, metric or error belongs to: the runner's metric label, not a tick field."""
ATTR_DEADLINE_POLICY: Final = "openral.tick.deadline_policy"
"""The overrun policy, on the deadline-missed event: configuration, not a tick field."""

# Other attributes
ATTR_SENSOR_ID: Final = "openral.sensor.id"
ATTR_SENSOR_AGE_MS: Final = "openral.sensors.age_ms"
ATTR_SYNC_SKEW_MS: Final = "openral.sensors.sync_skew_ms"
ATTR_THUMBNAIL_WIDTH: Final = "openral.thumbnail.width"
ATTR_THUMBNAIL_HEIGHT: Final = "openral.thumbnail.height"
ATTR_THUMBNAIL_JPEG_B64: Final = "openral.thumbnail.jpeg_b64"
ATTR_HAL_ADAPTER: Final = "openral.hal.adapter"
ATTR_HAL_ROBOT_MODEL: Final = "openral.hal.robot.model"
ATTR_HAL_CONTROL_MODE: Final = "openral.hal.control_mode"
ATTR_SAFETY_CHECK_NAME: Final = "check_name"
ATTR_SAFETY_SEVERITY: Final = "severity"
ATTR_SAFETY_CONTROL_MODE: Final = "safety.control_mode"
ATTR_SAFETY_HORIZON: Final = "safety.horizon"
ATTR_SAFETY_REQUESTED: Final = "safety.requested"
ATTR_SAFETY_SENT: Final = "safety.sent"
ATTR_SAFETY_REPLACED: Final = "safety.replaced"
ATTR_SAFETY_MAX_EE_SPEED: Final = "safety.envelope_max_ee_speed_m_s"
ATTR_SAFETY_MAX_FORCE: Final = "safety.envelope_max_force_n"
ATTR_COMPONENT: Final = "openral.world_state.component"
ATTR_CLI_COMMAND: Final = "openral.cli.command"
ATTR_CLI_CONFIG: Final = "openral.cli.config"
ATTR_RUN_STOP_REASON: Final = "openral.run.stop_reason"
ATTR_RUN_TICKS: Final = "openral.run.ticks"
ATTR_ESTOP_REASON: Final = "openral.estop.reason"
ATTR_SYNC_FAILURE: Final = "openral.sensors.sync_failure"
# OpenTelemetry's own keys, for an exception's text and type on events that are not exceptions.
ATTR_EXCEPTION_MESSAGE: Final = "exception.message"
ATTR_EXCEPTION_TYPE: Final = "exception.type"

# Events (on the span of the phase where they happen; the tick span for deadline and drop)
EVENT_DEADLINE_MISSED: Final = "openral.event.deadline_missed"
EVENT_TAKEOVER: Final = "openral.event.takeover"
"""Control passed between the policy and the takeover skill (attribute ``openral.takeover.active_skill``)."""
EVENT_SENSOR_STALE: Final = "openral.event.sensor_stale"
EVENT_STALENESS_LATCHED: Final = "openral.event.staleness_latched"
EVENT_ERROR_LATCHED: Final = "openral.event.error_latched"
EVENT_SAFETY_VIOLATION: Final = "openral.event.safety_violation"
EVENT_INVALID_ACTION: Final = "openral.event.invalid_action"
EVENT_SKILL_DONE: Final = "openral.event.skill_done"
EVENT_ACTION_DROPPED: Final = "openral.event.action_dropped"
EVENT_ESTOP_REQUESTED: Final = "openral.event.estop_requested"
EVENT_TICK_FAILED: Final = "openral.event.tick_failed"
EVENT_SENSOR_SYNC_FAILED: Final = "openral.event.sensor_sync_failed"

# Metrics
METRIC_TICK_DURATION: Final = "openral.tick.duration"
METRIC_INFERENCE_DURATION: Final = "openral.inference.duration"
METRIC_HAL_READ_STATE_DURATION: Final = "openral.hal.read_state.duration"
METRIC_HAL_SEND_ACTION_DURATION: Final = "openral.hal.send_action.duration"
METRIC_SENSORS_AGE: Final = "openral.sensors.age_ms"
METRIC_WORLD_STATE_STALENESS: Final = "openral.world_state.staleness_ms"
METRIC_WORLD_STATE_COMPONENTS_STALE: Final = "openral.world_state.components_stale"
METRIC_DEADLINE_MISSES: Final = "openral.tick.deadline_misses"
METRIC_BUDGET_VIOLATIONS: Final = "openral.tick.budget_violations"
METRIC_MISSED_SLOTS: Final = "openral.tick.missed_slots"
METRIC_SAFETY_VIOLATIONS: Final = "openral.safety.violations"
METRIC_SENSORS_STALE_READS: Final = "openral.sensors.stale_reads"
METRIC_ACTIONS_WITHHELD: Final = "openral.tick.actions_withheld"
METRIC_TAKEOVER_SWITCHES: Final = "openral.takeover.switches"
"""Times control passed between the policy and the takeover skill (counter, by the skill now driving)."""
METRIC_RECORDING_FRAMES: Final = "openral.recording.frames"
"""Dataset rows written (counter)."""
METRIC_RECORDING_REPEATED_FRAMES: Final = "openral.recording.repeated_frames"
"""Video frames repeated because a camera had no frame or its encoder fell behind (counter, per sensor)."""
METRIC_RECORDING_DROPPED_TICKS: Final = "openral.recording.dropped_ticks"
"""Ticks of an episode that never reached the dataset: the recorder's queue was full (counter)."""
METRIC_RECORDING_EPISODE_CLOSE: Final = "openral.recording.episode_close"
"""Time to commit an episode, ms (histogram)."""

# Chunked execution (openral_rskill.executor)
SPAN_EXECUTOR_CHUNK: Final = "openral.executor.chunk"
"""One chunk request: from the tick that asks (its parent) until its result is taken in or given up on."""
ATTR_EXECUTOR_REQUEST_ID: Final = "openral.executor.request_id"
ATTR_EXECUTOR_OBS_TICK: Final = "openral.executor.obs_tick"
ATTR_EXECUTOR_READY_TICK: Final = "openral.executor.ready_tick"
ATTR_EXECUTOR_DELAY_TICKS: Final = "openral.executor.delay_ticks"
ATTR_EXECUTOR_ROWS_SKIPPED: Final = "openral.executor.rows_skipped"
ATTR_EXECUTOR_ROWS_USED: Final = "openral.executor.rows_used"
ATTR_EXECUTOR_DISCARDED: Final = "openral.executor.discarded"
"""Why a chunk was not used: ``stale_epoch``, ``late``, ``error``, ``bad_shape``, ``too_few_rows``."""
METRIC_EXECUTOR_DELAY: Final = "openral.executor.delay_ticks"
"""Ticks from a chunk's observation to its use (histogram, unit ticks)."""
METRIC_EXECUTOR_STARVED_TICKS: Final = "openral.executor.starved_ticks"
"""Ticks with no chunk row for them: the last target held (counter)."""
METRIC_EXECUTOR_DISCARDED: Final = "openral.executor.discarded_chunks"
"""Chunks not used, by ``openral.executor.discarded`` reason (counter)."""
METRIC_EXECUTOR_UNAVAILABLE_TICKS: Final = "openral.executor.unavailable_ticks"
"""Ticks on which the policy's source was down and the fallback decided (counter)."""

# Remote inference (openral_remote)
SPAN_REMOTE_REQUEST: Final = "openral.remote.request"
"""The client's side of one inference request: encode, the round trip, decode."""
SPAN_REMOTE_INFER: Final = "openral.remote.infer"
"""The server's side of one inference request (a child of the client's request span, across machines)."""
ATTR_REMOTE_KEY: Final = "openral.remote.key"
ATTR_REMOTE_OUTCOME: Final = "openral.remote.outcome"
"""``ok``, ``unavailable`` (no reply), ``timeout``, ``superseded``, ``error``."""
ATTR_REMOTE_REQUEST_BYTES: Final = "openral.remote.request_bytes"
ATTR_REMOTE_REPLY_BYTES: Final = "openral.remote.reply_bytes"
ATTR_REMOTE_QUEUE_MS: Final = "openral.remote.queue_ms"
"""Server: how long the request waited for the worker."""
ATTR_REMOTE_BATCH_SIZE: Final = "openral.remote.batch_size"
"""Server: requests in the inference this one ran in (1: alone)."""
METRIC_REMOTE_ROUND_TRIP: Final = "openral.remote.round_trip"
"""Client: request to decoded reply, ms (histogram)."""
METRIC_REMOTE_FAILURES: Final = "openral.remote.failures"
"""Client: requests without a chunk, by ``openral.remote.outcome`` (counter)."""
METRIC_REMOTE_SERVER_CHANGES: Final = "openral.remote.server_changes"
"""Client: the server went down or came back, by ``openral.remote.outcome`` (``down``, ``up``, ``refused``)."""

# Perception events (openral_perception)
SPAN_PERCEPTION_DETECT: Final = "openral.perception.detect"
"""One detector run on one frame (off the tick thread)."""
EVENT_PERCEPTION: Final = "openral.event.perception"
"""A detector found something (on its detect span)."""
ATTR_PERCEPTION_KIND: Final = "openral.perception.kind"
ATTR_PERCEPTION_SUMMARY: Final = "openral.perception.summary"
METRIC_PERCEPTION_EVENTS: Final = "openral.perception.events"
"""Events published, by kind (counter)."""
METRIC_PERCEPTION_DROPPED: Final = "openral.perception.dropped_frames"
"""Frames a detector never looked at: rate-limited (by kind) or superseded by a newer one (counter)."""

# The world around the robot as a picture (openral_perception.world_cloud)
SPAN_WORLD_CLOUD: Final = "openral.world_cloud"
"""One picture of the point cloud around the base, its figures as attributes (a span with no children)."""
ATTR_WORLD_CLOUD_FRAME_ID: Final = "openral.world_cloud.frame_id"
ATTR_WORLD_CLOUD_SOURCE_NODE: Final = "openral.world_cloud.source_node"
ATTR_WORLD_CLOUD_POINTS_TOTAL: Final = "openral.world_cloud.points_total"
ATTR_WORLD_CLOUD_POINTS_IN_BOX: Final = "openral.world_cloud.points_in_box"
ATTR_WORLD_CLOUD_NEAREST_M: Final = "openral.world_cloud.nearest_m"
"""Distance of the nearest point in the box (-1 when the box is empty)."""
ATTR_WORLD_CLOUD_RANGE_MAX_M: Final = "openral.world_cloud.range_max_m"
ATTR_WORLD_CLOUD_BOX_XY_M: Final = "openral.world_cloud.box_xy_m"
ATTR_WORLD_CLOUD_BOX_Z_M: Final = "openral.world_cloud.box_z_m"
ATTR_WORLD_CLOUD_PNG_BASE64: Final = "openral.world_cloud.png_base64"

# Log records (structlog → OpenTelemetry): the keys that carry the current span's ids
LOG_TRACE_ID: Final = "trace_id"
LOG_SPAN_ID: Final = "span_id"
