"""What a runner reports: one ``TickResult`` per tick, one ``RunResult`` per run.

Each ``TickResult`` field says, in its annotation, where else it is rendered: a
:class:`SpanAttribute` names its attribute on the ``rskill.tick`` span, a :class:`DatasetColumn`
gives its recorded column. The telemetry table (``openral_observability.semconv.TICK_ATTRIBUTES``)
and the dataset's ``openral.*`` columns (``openral_dataset.schema``) are read off them, so a new
tick field is one line here; the runner's ``TickContext`` carries it, under its name and type, once
a phase has a value for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field


class WithheldReason(StrEnum):
    """Why a tick's action did not reach ``HAL.send_action``.

    The fault reasons (:attr:`is_fault`) count towards ``faults.max_consecutive_failures``.
    """

    DEADLINE = "deadline"
    SAFETY = "safety"
    STALE_SENSOR = "stale_sensor"
    READ_STATE = "read_state"
    SKILL_ERROR = "skill_error"
    INVALID_ACTION = "invalid_action"
    HAL_ERROR = "hal_error"
    ESTOP = "estop"
    SKILL_DONE = "skill_done"
    """The skill finished its task (raised ``ROSStopRequested``): nothing to send, the run ends."""
    AWAITING_CHUNK = "awaiting_chunk"
    """A chunking policy's first chunk has not arrived yet: nothing to send, nothing to hold."""
    STARVED = "starved"
    """No chunk row came for too many ticks and the fallback is to stop (or there is no fallback skill)."""

    @property
    def is_fault(self) -> bool:
        """Whether this reason is a failed tick (a component failed, not a policy decision)."""
        return self in _FAULTS


class StopReason(StrEnum):
    """Why ``run()`` returned."""

    MAX_TICKS = "max_ticks"
    DURATION = "duration"
    TERMINATED = "terminated"
    """The runner's own end condition (a simulation's episode count)."""
    STOP_REQUESTED = "stop_requested"
    SKILL_DONE = "skill_done"
    """The skill raised ``ROSStopRequested``: its task is done."""
    DEADLINE = "deadline"
    ESTOP = "estop"
    FAULTS = "faults"
    SIGINT = "signal:SIGINT"
    SIGTERM = "signal:SIGTERM"


@dataclass(frozen=True)
class SpanAttribute:
    """A ``TickResult`` field's attribute on the ``rskill.tick`` span (how it is rendered follows from its type).

    The spec's ``skill.<field>`` where the spec names the fact; otherwise ``openral.tick.*``, or
    ``openral.takeover.*`` for what a takeover skill adds. A field without one stays off the span.
    """

    name: str


ColumnType = Literal["int64", "float32", "bool", "string", "actions"]
"""A recorded column's dtype; ``actions``: one float32 per action name."""


@dataclass(frozen=True)
class DatasetColumn:
    """A ``TickResult`` field recorded as it is, one dataset column per tick (``None`` is the column's absent value).

    The column is ``openral.<field>`` unless ``name`` gives another (kept for datasets already recorded).
    ``takeover``: recorded only by a deployment with a takeover skill. A field without one is not a column.
    """

    dtype: ColumnType
    name: str | None = None
    takeover: bool = False


_FAULTS = frozenset(
    {
        WithheldReason.STALE_SENSOR,
        WithheldReason.READ_STATE,
        WithheldReason.SKILL_ERROR,
        WithheldReason.INVALID_ACTION,
        WithheldReason.HAL_ERROR,
        WithheldReason.STARVED,
    }
)


class TickResult(BaseModel):
    """The record of one tick: the one description every renderer of a tick derives from.

    The runner builds it once per tick (``TickContext``); the tick span's attributes, the Foxglove
    message and its JSON Schema, the ROS 2 bag record and the dataset's ``openral.*`` columns are
    rendered from its fields. A field's span attribute and dataset column are declared beside it
    (:class:`SpanAttribute`, :class:`DatasetColumn`): a field added here, with them, reaches every
    renderer with no other edit.

    Phase timings are milliseconds on the runner's clock. The optional fields are ``None`` when
    they do not apply, so ``model_dump(exclude_none=True)`` carries only what the tick had:
    ``episode_idx`` and ``step_idx`` are set while an episode is open (recorded on hardware as in
    simulation); ``reward``, ``terminated`` and ``truncated`` come from a simulator's step.

    Attributes:
        start_ns: Tick start on the runner clock, in nanoseconds.
        lateness_ms: How far past the tick's deadline the action was ready (0 if on time).
        deadline_missed: ``lateness_ms`` is above 0.
        action_applied: The action reached ``HAL.send_action``.
        withheld_reason: Why it did not (see :class:`WithheldReason`), ``None`` when applied.
        requested_action / sent_action: Row 0 before and after the safety client, when they differ
            the safety client clamped.
        trace_context: The tick span's W3C ``traceparent``, ``None`` when the tick was not traced.
        step_idx: The tick's step within the open episode, from 0.
        intervention: With a takeover skill configured: a person drove this tick (``None`` without one).
        active_skill: With a takeover skill configured: the skill whose action this tick was.
        policy_action: With a takeover skill configured: row 0 of what the policy proposed this tick,
            also while the person drove (DAgger labels); ``None`` when it proposed nothing.
        handover_ramp: With a takeover skill configured: the command was limited to one envelope
            step towards the active skill's target, just after control passed (bumpless transfer).
    """

    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    tick_idx: Annotated[int, SpanAttribute("openral.tick.idx"), DatasetColumn("int64")] = Field(ge=0)
    start_ns: Annotated[int, DatasetColumn("int64", name="openral.tick_start_ns")] = 0
    tick_ms: Annotated[float, SpanAttribute("skill.tick_ms")] = 0.0
    sensors_ms: Annotated[float, SpanAttribute("skill.sensors_ms")] = Field(
        default=0.0,
        description=(
            "Time to read the robot's state and its sensors for this tick, before the world state is built and the "
            "skill is asked: on a robot, each camera's latest frame and HAL.read_state; in simulation, rendering the "
            "cameras on the last step's observation (its state came with the step)."
        ),
    )
    world_state_ms: Annotated[float, SpanAttribute("skill.world_state_ms")] = Field(
        default=0.0,
        description=(
            "Time to build the world state the skill sees from what was read: on a robot, the aggregator's snapshot "
            "with its verdict on every component; in simulation, assembling it from the observation and the frames."
        ),
    )
    inference_ms: Annotated[float, SpanAttribute("skill.inference_ms")] = 0.0
    safety_ms: Annotated[float, SpanAttribute("skill.safety_ms")] = 0.0
    hal_ms: Annotated[float, SpanAttribute("skill.hal_ms")] = 0.0
    lateness_ms: Annotated[float, SpanAttribute("openral.tick.lateness_ms"), DatasetColumn("float32")] = 0.0
    deadline_missed: bool = False
    action_applied: Annotated[bool, SpanAttribute("skill.action_applied"), DatasetColumn("bool")] = False
    withheld_reason: Annotated[
        WithheldReason | None, SpanAttribute("skill.withheld_reason"), DatasetColumn("string")
    ] = None
    safety_violations: Annotated[list[str], SpanAttribute("skill.safety_violations")] = Field(default_factory=list)
    stale_sensors: list[str] = Field(default_factory=list)
    requested_action: Annotated[list[float] | None, DatasetColumn("actions")] = None
    sent_action: list[float] | None = None
    trace_context: str | None = None
    step_idx: Annotated[int | None, SpanAttribute("skill.step_idx")] = Field(default=None, ge=0)
    episode_idx: Annotated[int | None, SpanAttribute("skill.episode_idx")] = Field(default=None, ge=0)
    reward: Annotated[float | None, SpanAttribute("skill.reward")] = None
    terminated: Annotated[bool | None, SpanAttribute("skill.terminated")] = None
    truncated: Annotated[bool | None, SpanAttribute("skill.truncated")] = None
    intervention: Annotated[
        bool | None, SpanAttribute("openral.takeover.intervention"), DatasetColumn("bool", takeover=True)
    ] = None
    active_skill: Annotated[
        str | None, SpanAttribute("openral.takeover.active_skill"), DatasetColumn("string", takeover=True)
    ] = None
    policy_action: Annotated[list[float] | None, DatasetColumn("actions", takeover=True)] = None
    handover_ramp: Annotated[
        bool | None, SpanAttribute("openral.takeover.ramp"), DatasetColumn("bool", takeover=True)
    ] = None

    @classmethod
    def trusted(cls, values: dict[str, Any]) -> TickResult:
        """A ``TickResult`` of values a runner computed itself, without validating them again.

        ``values`` must hold every field, already of its type (the runner's ``TickContext`` builds
        it); nothing is defaulted or coerced, and the dict becomes the result's own. About a
        sixth of the cost of validated construction, on a path taken every tick. Input from
        outside (a file, a network peer) goes through ``TickResult(...)`` or ``model_validate``.
        """
        result = _new(cls)
        _set(result, "__dict__", values)
        _set(result, "__pydantic_fields_set__", set(_ALL_TICK_FIELDS))
        _set(result, "__pydantic_extra__", None)
        _set(result, "__pydantic_private__", None)
        return result


_ALL_TICK_FIELDS = frozenset(TickResult.model_fields)
_new = object.__new__
_set = object.__setattr__

_Marker = TypeVar("_Marker", SpanAttribute, DatasetColumn)


def tick_fields_with(marker: type[_Marker]) -> dict[str, _Marker]:
    """Each ``TickResult`` field annotated with a ``marker``, in field order, with it."""
    out: dict[str, _Marker] = {}
    for name, info in TickResult.model_fields.items():
        found = [item for item in info.metadata if isinstance(item, marker)]
        if len(found) > 1:
            raise TypeError(f"TickResult.{name} has {len(found)} {marker.__name__} annotations, expected at most one")
        if found:
            out[name] = found[0]
    return out


class RunResult(BaseModel):
    """Honest timing and fault totals for one ``run()``.

    Attributes:
        duration_s: Wall time of the run, to the end of its last tick (see the field).
        effective_rate_hz: The rate the ticks started at, over their own span (see the field); not
            ``n_ticks / duration_s``, which also counts the last tick's own time.
        start_jitter_us_*: How late each tick started relative to its scheduled slot.
        missed_slots: Slots skipped after overruns (the loop never bursts to catch up).
        overhead_us_mean: Tick time not spent in the five phases (runner bookkeeping).
        stop_reason: Why the run ended (see :class:`StopReason`).
    """

    model_config = ConfigDict(extra="forbid")

    runner_name: str = "inference_runner"
    skill_id: str | None = None
    rate_hz: float = Field(gt=0, description="The rate asked for (ticks per second).")
    n_ticks: int = Field(ge=0, description="Ticks run.")
    duration_s: float = Field(
        default=0.0,
        ge=0,
        description="Wall time of the run: from its start (slot 0 of the schedule) to the end of its last tick. "
        "It includes the last tick's own time and any stall in it, so n_ticks / duration_s reads below "
        "effective_rate_hz by that much (at 10 kHz, a last tick of 4 ms in a 1000-tick run: about 4 %).",
    )
    effective_rate_hz: float = Field(
        default=0.0,
        ge=0,
        description="The rate the ticks started at: (n_ticks - 1) / (last tick's start - first tick's start); "
        "0 with fewer than two ticks. A run that kept its schedule reads rate_hz exactly, whatever its last "
        "tick took; a stall in it shows in tick_ms_max and missed_slots instead.",
    )
    tick_ms_mean: float = 0.0
    tick_ms_p50: float = 0.0
    tick_ms_p99: float = 0.0
    tick_ms_max: float = 0.0
    inference_ms_mean: float = 0.0
    inference_ms_p50: float = 0.0
    inference_ms_p99: float = 0.0
    inference_ms_max: float = 0.0
    start_jitter_us_p50: float = 0.0
    start_jitter_us_p99: float = 0.0
    start_jitter_us_max: float = 0.0
    overhead_us_mean: float = 0.0
    missed_slots: int = Field(default=0, ge=0)
    deadline_misses: int = Field(default=0, ge=0)
    budget_violations: int = Field(default=0, ge=0)
    dropped_actions: int = Field(default=0, ge=0)
    withheld_actions: int = Field(default=0, ge=0)
    stale_reads: int = Field(default=0, ge=0)
    safety_violations: int = Field(default=0, ge=0)
    failed_ticks: int = Field(default=0, ge=0)
    stop_reason: StopReason = StopReason.MAX_TICKS
    trace_id: str | None = None
    metadata: dict[str, Any] = Field(default_factory=dict)
