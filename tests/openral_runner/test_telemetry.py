"""The runner's telemetry: one span tree per tick, events at the fault boundaries, metrics counted once."""

from __future__ import annotations

from typing import Any

import pytest
from opentelemetry import trace

from openral_core import (
    Action,
    DeadlineOverrunPolicy,
    ROSEStopRequested,
    ROSHardwareError,
    ROSSafetyViolation,
    SafetyEnvelope,
    SensorReaderConfig,
)
from openral_hal.testing import RecordingHAL
from openral_observability import semconv
from openral_observability.propagation import extract
from openral_rskill.testing import ScriptedSkill
from openral_runner.hardware import HardwareRunner
from openral_runner.safety import SafetyClient
from openral_runner.testing import FakeClock, ScriptedReader
from openral_world_state import WorldStateAggregator

JOINTS = ["j0", "j1", "j2"]
RATE = 50.0
PERIOD = 1.0 / RATE
PHASES = {
    semconv.SPAN_SENSORS_READ,
    semconv.SPAN_HAL_READ_STATE,
    semconv.SPAN_WORLD_STATE_SNAPSHOT,
    semconv.SPAN_SKILL_INFERENCE,
    semconv.SPAN_SAFETY_CHECK,
    semconv.SPAN_HAL_SEND_ACTION,
}


class RejectingSafety(SafetyClient):
    """Rejects actions whose first target is negative; e-stops on 99."""

    envelope = SafetyEnvelope()

    def check_action(self, action: Action) -> Action | None:
        if action.first[0] == 99.0:
            raise ROSEStopRequested("stop button")
        if action.first[0] < 0:
            raise ROSSafetyViolation(f"j0 target {action.first[0]} below 0", check_name="joint_limit")
        return None


def build(
    clock: FakeClock,
    *,
    skill: ScriptedSkill | None = None,
    readers: list[ScriptedReader] | None = None,
    skill_id: str = "telemetry-test",
    sensors_required: bool = True,
    **kwargs: Any,
) -> HardwareRunner:
    skill = skill or ScriptedSkill(JOINTS, skill_id=skill_id)
    skill.configure()
    skill.activate()
    readers = readers or [ScriptedReader("front", clock)]
    configs = [SensorReaderConfig(sensor_id=r.sensor_id, required=sensors_required) for r in readers]
    runner = HardwareRunner(
        hal=RecordingHAL(JOINTS, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(joint_max_age_ms=100.0, sensors=configs, clock=clock.now_ns),
        sensor_readers=readers,
        rate_hz=RATE,
        clock=clock,
        **kwargs,
    )
    runner.activate()
    return runner


def rows(*values: float) -> list[list[float]]:
    return [[v, 0.0, 0.0] for v in values]


def events(spans: list[Any], name: str) -> list[tuple[Any, Any]]:
    """(span, event) for every event called ``name``."""
    return [(span, event) for span in spans for event in span.events if event.name == name]


def test_each_tick_is_one_span_with_the_phases_as_children(telemetry: Any) -> None:
    clock = FakeClock()
    runner = build(clock)
    result = runner.run(3)
    ticks = telemetry.spans(semconv.SPAN_TICK)
    assert len(ticks) == 3
    by_parent: dict[int, list[str]] = {}
    for span in telemetry.spans():
        if span.parent is not None:
            by_parent.setdefault(span.parent.span_id, []).append(span.name)
    for tick in ticks:
        children = by_parent[tick.context.span_id]
        assert set(children) == PHASES
        assert len(children) == len(PHASES)  # one reader: one of each
        assert tick.parent is None  # nothing enclosed the run
    assert len({tick.context.trace_id for tick in ticks}) == 3  # each root tick is its own trace
    assert result.trace_id == f"{ticks[0].context.trace_id:032x}"


def test_tick_span_carries_the_phase_timings(telemetry: Any) -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, skill_id="timed", on_step=lambda _i: clock.advance(0.004))
    runner = build(clock, skill=skill)
    runner.run(2)
    (first, second) = telemetry.spans(semconv.SPAN_TICK)
    for span, tick in zip((first, second), runner.recent_ticks, strict=True):
        attrs = span.attributes
        assert attrs[semconv.ATTR_TICK_IDX] == tick.tick_idx
        assert attrs[semconv.ATTR_SKILL_ID] == "timed"
        assert attrs[semconv.ATTR_INFERENCE_MS] == pytest.approx(4.0)
        for key, field in (
            (semconv.ATTR_TICK_MS, "tick_ms"),
            (semconv.ATTR_SENSORS_MS, "sensors_ms"),
            (semconv.ATTR_WORLD_STATE_MS, "world_state_ms"),
            (semconv.ATTR_INFERENCE_MS, "inference_ms"),
            (semconv.ATTR_SAFETY_MS, "safety_ms"),
            (semconv.ATTR_HAL_MS, "hal_ms"),
        ):
            assert attrs[key] == getattr(tick, field), key
        assert attrs[semconv.ATTR_ACTION_APPLIED] is True
        assert attrs[semconv.ATTR_SAFETY_VIOLATIONS] == 0


def test_trace_context_is_the_tick_spans_traceparent(telemetry: Any) -> None:
    runner = build(FakeClock())
    runner.run(2)
    spans = telemetry.spans(semconv.SPAN_TICK)
    for span, tick in zip(spans, runner.recent_ticks, strict=True):
        ctx = span.context
        assert ctx.trace_flags.sampled
        assert tick.trace_context == f"00-{ctx.trace_id:032x}-{ctx.span_id:016x}-{int(ctx.trace_flags):02x}"
        parent = trace.get_current_span(extract({"traceparent": tick.trace_context})).get_span_context()
        assert (parent.trace_id, parent.span_id) == (ctx.trace_id, ctx.span_id)


def test_ticks_nest_under_the_enclosing_span_and_share_its_trace(telemetry: Any) -> None:
    runner = build(FakeClock())
    with trace.get_tracer("test").start_as_current_span(semconv.SPAN_CLI_COMMAND) as root:
        result = runner.run(4)
    root_ctx = root.get_span_context()
    ticks = telemetry.spans(semconv.SPAN_TICK)
    assert len(ticks) == 4
    assert all(t.parent is not None and t.parent.span_id == root_ctx.span_id for t in ticks)
    assert {t.context.trace_id for t in ticks} == {root_ctx.trace_id}
    assert result.trace_id == f"{root_ctx.trace_id:032x}"


def test_spans_a_skill_opens_nest_under_the_inference_span(telemetry: Any) -> None:
    def step(_i: int) -> None:
        with trace.get_tracer("skill").start_as_current_span("policy.forward"):
            pass

    runner = build(FakeClock(), skill=ScriptedSkill(JOINTS, on_step=step))
    runner.run(1)
    (forward,) = telemetry.spans("policy.forward")
    (inference,) = telemetry.spans(semconv.SPAN_SKILL_INFERENCE)
    assert forward.parent.span_id == inference.context.span_id


def test_deadline_miss_is_an_event_on_the_tick_and_a_counted_metric(telemetry: Any) -> None:
    clock = FakeClock()
    late = {1, 3}
    skill = ScriptedSkill(
        JOINTS, skill_id="late", on_step=lambda i: clock.advance(PERIOD * 1.5 if i in late else 0.001)
    )
    runner = build(clock, skill=skill, deadline_overrun_policy=DeadlineOverrunPolicy.DROP)
    result = runner.run(5)
    assert result.deadline_misses == 2
    assert result.dropped_actions == 2
    ticks = telemetry.spans(semconv.SPAN_TICK)
    missed = events(ticks, semconv.EVENT_DEADLINE_MISSED)
    assert [span.attributes[semconv.ATTR_TICK_IDX] for span, _ in missed] == [1, 3]
    for span, event in missed:
        assert event.attributes[semconv.ATTR_LATENESS_MS] == pytest.approx(PERIOD * 0.5 * 1e3, rel=0.05)
        assert event.attributes[semconv.ATTR_DEADLINE_POLICY] == "drop"
        assert span.attributes[semconv.ATTR_WITHHELD_REASON] == "deadline"
        assert span.attributes[semconv.ATTR_LATENESS_MS] > 0
    dropped = events(ticks, semconv.EVENT_ACTION_DROPPED)
    assert len(dropped) == 2
    assert telemetry.metric(semconv.METRIC_DEADLINE_MISSES, **{semconv.ATTR_SKILL_ID: "late"}) == 2
    withheld = {semconv.ATTR_SKILL_ID: "late", semconv.ATTR_WITHHELD_REASON: "deadline"}
    assert telemetry.metric(semconv.METRIC_ACTIONS_WITHHELD, **withheld) == 2
    # Dropped late actions never reached the HAL: no send span on those ticks.
    assert len(telemetry.spans(semconv.SPAN_HAL_SEND_ACTION)) == 3


def test_stale_sensor_is_an_event_on_its_read_span_and_a_counted_metric(telemetry: Any) -> None:
    clock = FakeClock()
    front = ScriptedReader("front", clock)
    wrist = ScriptedReader("wrist-stale-test", clock, max_age_ms=100.0)
    ages = iter([1.0])  # fresh when the run starts (it waits for that), stale on every tick after
    wrist.on_read = lambda: setattr(wrist, "age_ms", next(ages, 500.0))
    runner = build(clock, readers=[front, wrist])
    result = runner.run(3)
    assert result.stale_reads == 3
    stale = events(telemetry.spans(semconv.SPAN_SENSORS_READ), semconv.EVENT_SENSOR_STALE)
    assert len(stale) == 3
    for _span, event in stale:
        assert event.attributes[semconv.ATTR_SENSOR_ID] == "wrist-stale-test"
        assert event.attributes[semconv.ATTR_SENSOR_AGE_MS] == 500.0
    assert telemetry.metric(semconv.METRIC_SENSORS_STALE_READS, **{semconv.ATTR_SENSOR_ID: "wrist-stale-test"}) == 3
    assert telemetry.metric(semconv.METRIC_SENSORS_STALE_READS, **{semconv.ATTR_SENSOR_ID: "front"}) == 0
    # The aggregator latches the staleness once, on the first snapshot, not every tick.
    latched = events(telemetry.spans(semconv.SPAN_WORLD_STATE_SNAPSHOT), semconv.EVENT_STALENESS_LATCHED)
    assert [e.attributes[semconv.ATTR_COMPONENT] for _s, e in latched] == ["wrist-stale-test"]
    # The fresh camera's age is recorded on every read.
    assert telemetry.metric(semconv.METRIC_SENSORS_AGE, **{semconv.ATTR_SENSOR_ID: "front"}) == 3


def test_a_safety_violation_is_counted_exactly_once(telemetry: Any) -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, skill_id="unsafe", actions=rows(0.1, -0.5, 0.2))
    runner = build(clock, skill=skill, safety_client=RejectingSafety())
    result = runner.run(3)
    assert result.safety_violations == 1
    spans = telemetry.spans()
    violations = events(spans, semconv.EVENT_SAFETY_VIOLATION)
    assert len(violations) == 1
    span, event = violations[0]
    assert span.name == semconv.SPAN_SAFETY_CHECK
    assert event.attributes[semconv.ATTR_SAFETY_CHECK_NAME] == "joint_limit"
    assert "below 0" in event.attributes[semconv.ATTR_EXCEPTION_MESSAGE]
    assert len(events(spans, "exception")) == 1  # record_exception on the same span, once
    assert telemetry.metric(semconv.METRIC_SAFETY_VIOLATIONS) == 1  # over every label set
    assert telemetry.metric(semconv.METRIC_SAFETY_VIOLATIONS, **{semconv.ATTR_SAFETY_CHECK_NAME: "joint_limit"}) == 1
    ticks = telemetry.spans(semconv.SPAN_TICK)
    assert [t.attributes[semconv.ATTR_SAFETY_VIOLATIONS] for t in ticks] == [0, 1, 0]
    assert ticks[1].attributes[semconv.ATTR_WITHHELD_REASON] == "safety"
    withheld = {semconv.ATTR_SKILL_ID: "unsafe", semconv.ATTR_WITHHELD_REASON: "safety"}
    assert telemetry.metric(semconv.METRIC_ACTIONS_WITHHELD, **withheld) == 1


def test_estop_is_an_event_and_an_estop_span(telemetry: Any) -> None:
    skill = ScriptedSkill(JOINTS, actions=rows(0.1, 99.0))
    runner = build(FakeClock(), skill=skill, safety_client=RejectingSafety())
    result = runner.run(5)
    assert result.stop_reason == "estop"
    spans = telemetry.spans()
    (estop_event,) = events(spans, semconv.EVENT_ESTOP_REQUESTED)
    assert estop_event[0].name == semconv.SPAN_SAFETY_CHECK
    assert estop_event[1].attributes[semconv.ATTR_ESTOP_REASON] == "stop button"
    assert len(telemetry.spans(semconv.SPAN_HAL_ESTOP)) == 1
    assert events(spans, semconv.EVENT_SAFETY_VIOLATION) == []  # an e-stop is not an ordinary violation
    assert telemetry.metric(semconv.METRIC_SAFETY_VIOLATIONS) == 0


def test_duration_metrics_have_one_point_per_tick(telemetry: Any) -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, skill_id="metered", on_step=lambda _i: clock.advance(0.002))
    runner = build(clock, skill=skill, latency_budget_ms=1.0)
    result = runner.run(4)
    skill_label = {semconv.ATTR_SKILL_ID: "metered"}
    assert telemetry.metric(semconv.METRIC_TICK_DURATION, **skill_label) == 4
    assert telemetry.metric(semconv.METRIC_TICK_DURATION, field="sum", **skill_label) == pytest.approx(
        sum(t.tick_ms for t in runner.recent_ticks)
    )
    assert telemetry.metric(semconv.METRIC_INFERENCE_DURATION, **skill_label) == 4
    assert telemetry.metric(semconv.METRIC_INFERENCE_DURATION, field="sum", **skill_label) == pytest.approx(8.0)
    hal_label = {semconv.ATTR_HAL_ADAPTER: "recordinghal"}
    assert telemetry.metric(semconv.METRIC_HAL_READ_STATE_DURATION, **hal_label) == 4
    assert telemetry.metric(semconv.METRIC_HAL_SEND_ACTION_DURATION, **hal_label) == 4
    # Each budget overrun is counted once, and the read-state histogram holds the read alone (no sensor time).
    assert result.budget_violations == 4
    assert telemetry.metric(semconv.METRIC_BUDGET_VIOLATIONS, **skill_label) == 4
    staleness = {semconv.ATTR_COMPONENT: "joint_state"}
    assert telemetry.metric(semconv.METRIC_WORLD_STATE_STALENESS, **staleness) >= 4


def test_live_status_reports_what_the_status_display_shows() -> None:
    clock = FakeClock()
    wrist = ScriptedReader("wrist", clock, age_ms=500.0, max_age_ms=100.0)
    skill = ScriptedSkill(JOINTS, actions=rows(0.1, -0.5, 0.2, 0.3))
    runner = build(clock, readers=[wrist], skill=skill, safety_client=RejectingSafety(), sensors_required=False)
    runner.run(4)
    status = runner.live_status()
    assert status["ticks"] == 4
    assert status["target_hz"] == RATE
    assert status["recent_rate_hz"] == pytest.approx(RATE)
    assert status["stale_sensors"] == 1
    assert status["stale_reads"] == 4
    assert status["safety_violations"] == 1
    assert status["tick_ms_p99"] >= status["tick_ms_p50"] >= 0
    assert {"deadline_misses", "missed_slots", "dropped_actions", "withheld_actions", "rate_hz"} <= set(status)


class HalvingSafety(SafetyClient):
    """A clamping client: sends every action with its targets halved."""

    envelope = SafetyEnvelope()

    def check_action(self, action: Action) -> Action | None:
        return action.model_copy(update={"targets": [[v / 2 for v in action.first]]})


def test_safety_span_records_requested_and_sent(telemetry: Any) -> None:
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, actions=rows(0.8, -0.4))
    runner = build(clock, skill=skill, safety_client=HalvingSafety())
    runner.run(1)
    runner.safety_client = RejectingSafety()
    runner.run(1)
    clamped, rejected = telemetry.spans(semconv.SPAN_SAFETY_CHECK)
    assert list(clamped.attributes[semconv.ATTR_SAFETY_REQUESTED]) == [0.8, 0.0, 0.0]
    assert list(clamped.attributes[semconv.ATTR_SAFETY_SENT]) == [0.4, 0.0, 0.0]
    assert clamped.attributes[semconv.ATTR_SAFETY_REPLACED] is True
    assert list(rejected.attributes[semconv.ATTR_SAFETY_REQUESTED]) == [-0.4, 0.0, 0.0]
    assert semconv.ATTR_SAFETY_SENT not in rejected.attributes


def test_deferred_phase_spans_are_children_of_their_tick_and_inside_it(telemetry: Any) -> None:
    clock = FakeClock()
    wrist = ScriptedReader("wrist-deferred-test", clock, age_ms=500.0, max_age_ms=100.0)
    runner = build(clock, readers=[ScriptedReader("front", clock), wrist], sensors_required=False)
    runner.tick()
    runner.tick()
    assert runner.flush_telemetry()
    ticks = {t.context.span_id: t for t in telemetry.spans(semconv.SPAN_TICK)}
    assert len(ticks) == 2
    deferred = {
        semconv.SPAN_SENSORS_READ,
        semconv.SPAN_HAL_READ_STATE,
        semconv.SPAN_WORLD_STATE_SNAPSHOT,
        semconv.SPAN_HAL_SEND_ACTION,
    }
    seen = 0
    for span in telemetry.spans():
        if span.name not in deferred:
            continue
        seen += 1
        tick = ticks[span.parent.span_id]
        assert span.context.trace_id == tick.context.trace_id
        assert tick.start_time <= span.start_time <= span.end_time <= tick.end_time
    assert seen == 2 * (len(deferred) + 1)  # two readers per tick
    # Events are replayed with the time they happened, inside their span.
    stale = events(telemetry.spans(semconv.SPAN_SENSORS_READ), semconv.EVENT_SENSOR_STALE)
    assert len(stale) == 2
    for span, event in stale:
        assert span.start_time <= event.timestamp <= span.end_time
        assert event.attributes[semconv.ATTR_SENSOR_ID] == "wrist-deferred-test"
    (latched,) = events(telemetry.spans(semconv.SPAN_WORLD_STATE_SNAPSHOT), semconv.EVENT_STALENESS_LATCHED)
    assert latched[0].start_time <= latched[1].timestamp <= latched[0].end_time


def test_a_phase_error_is_replayed_as_an_exception_and_an_error_status(telemetry: Any) -> None:
    class FailingHAL(RecordingHAL):
        def send_action(self, action: Action) -> None:
            raise ROSHardwareError("bus down")

    clock = FakeClock()
    skill = ScriptedSkill(JOINTS)
    skill.configure()
    skill.activate()
    runner = HardwareRunner(
        hal=FailingHAL(JOINTS, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(joint_max_age_ms=100.0, clock=clock.now_ns),
        rate_hz=RATE,
        clock=clock,
    )
    runner.activate()
    runner.run(1)
    (send,) = telemetry.spans(semconv.SPAN_HAL_SEND_ACTION)
    assert send.status.status_code is trace.StatusCode.ERROR
    (exception,) = send.events
    assert exception.name == "exception"
    assert "bus down" in exception.attributes["exception.message"]
    assert send.start_time <= exception.timestamp <= send.end_time
    runner.deactivate()


def test_metrics_are_recorded_for_ticks_the_sampler_dropped(telemetry: Any) -> None:
    runner = build(FakeClock(), skill_id="unsampled-metrics")
    with trace.use_span(trace.NonRecordingSpan(trace.SpanContext(1, 2, is_remote=True))):
        # A non-sampled parent: the default ParentBased sampler drops every tick.
        runner.run(3)
    assert telemetry.spans(semconv.SPAN_TICK) == []
    assert telemetry.metric(semconv.METRIC_TICK_DURATION, **{semconv.ATTR_SKILL_ID: "unsampled-metrics"}) == 3
    assert telemetry.metric(semconv.METRIC_HAL_READ_STATE_DURATION) == 3
