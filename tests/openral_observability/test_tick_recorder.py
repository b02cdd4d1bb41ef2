"""The tick recorder: ticks under an SDK tracer export as the SDK's own spans would; without one, API no-ops."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from opentelemetry import context, trace
from opentelemetry.sdk.trace import ReadableSpan, TracerProvider
from opentelemetry.sdk.trace.export import SimpleSpanProcessor
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter
from opentelemetry.sdk.trace.sampling import ALWAYS_OFF
from opentelemetry.trace import StatusCode

from openral_observability import semconv
from openral_observability.tick_recorder import TickRecorder


@pytest.fixture
def local() -> Iterator[tuple[TracerProvider, InMemorySpanExporter]]:
    """A private SDK provider with an in-memory exporter (the global one is the session's)."""
    exporter = InMemorySpanExporter()
    provider = TracerProvider()
    provider.add_span_processor(SimpleSpanProcessor(exporter))
    yield provider, exporter
    provider.shutdown()


def _by_name(exporter: InMemorySpanExporter) -> dict[str, ReadableSpan]:
    return {span.name: span for span in exporter.get_finished_spans()}


def test_recorded_tick_exports_a_tree_that_live_sdk_children_join(
    local: tuple[TracerProvider, InMemorySpanExporter],
) -> None:
    provider, exporter = local
    recorder = TickRecorder(provider)
    recorder.activate()
    try:
        assert recorder.defers_spans
        with provider.get_tracer("cli").start_as_current_span("cli.command") as root:
            batch = recorder.begin()
            tick = batch.span
            token = context.attach(trace.set_span_in_context(tick))
            phase = batch.start_span(semconv.SPAN_SKILL_INFERENCE, {"shared": True})
            inner = context.attach(trace.set_span_in_context(phase))
            with provider.get_tracer("skill").start_as_current_span("policy.forward"):
                pass  # a skill's own SDK span, started live under the deferred phase
            try:
                raise ValueError("bad action")
            except ValueError as exc:
                phase.record_exception(exc)
            phase.set_status(StatusCode.ERROR, "bad action")
            context.detach(inner)
            phase.end()
            context.detach(token)
            recorder.end(batch, {semconv.ATTR_TICK_IDX: 7})
            assert recorder.worker.flush()
    finally:
        recorder.deactivate()
    spans = _by_name(exporter)
    tick_span, phase_span, skill_span = (
        spans[semconv.SPAN_TICK],
        spans[semconv.SPAN_SKILL_INFERENCE],
        spans["policy.forward"],
    )
    root_ctx = root.get_span_context()
    assert tick_span.parent is not None
    assert tick_span.parent.span_id == root_ctx.span_id
    assert tick_span.context.trace_id == root_ctx.trace_id
    assert tick_span.context.trace_flags == root_ctx.trace_flags  # sampled, and random-trace-id as the root
    assert tick_span.attributes == {semconv.ATTR_TICK_IDX: 7}
    assert phase_span.parent is not None
    assert phase_span.parent.span_id == tick_span.context.span_id
    assert skill_span.parent is not None
    assert skill_span.parent.span_id == phase_span.context.span_id
    assert tick_span.start_time <= phase_span.start_time <= phase_span.end_time <= tick_span.end_time
    assert phase_span.status.status_code is StatusCode.ERROR
    (event,) = phase_span.events
    assert event.name == "exception"
    assert event.attributes["exception.type"] == "ValueError"
    assert event.attributes["exception.message"] == "bad action"
    assert "raise ValueError" in event.attributes["exception.stacktrace"]
    assert tick_span.resource is provider.resource
    assert tick_span.instrumentation_scope is not None
    assert tick_span.instrumentation_scope.name == semconv.TRACER_NAME
    assert batch.pending


def test_exception_event_matches_the_sdks_own(local: tuple[TracerProvider, InMemorySpanExporter]) -> None:
    provider, exporter = local
    recorder = TickRecorder(provider)
    recorder.activate()
    error = KeyError("joint")
    try:
        batch = recorder.begin()
        batch.span.record_exception(error, {"extra": 1})
        recorder.end(batch)
        assert recorder.worker.flush()
    finally:
        recorder.deactivate()
    live = provider.get_tracer("x").start_span("live")
    live.record_exception(error, {"extra": 1})
    live.end()
    deferred_event = _by_name(exporter)[semconv.SPAN_TICK].events[0]
    live_event = _by_name(exporter)["live"].events[0]
    assert dict(deferred_event.attributes or {}) == dict(live_event.attributes or {})


def test_an_unsampled_tick_records_nothing_and_phases_use_its_span() -> None:
    exporter = InMemorySpanExporter()
    provider = TracerProvider(sampler=ALWAYS_OFF)
    provider.add_span_processor(SimpleSpanProcessor(exporter))
    recorder = TickRecorder(provider)
    recorder.activate()
    try:
        batch = recorder.begin()
        assert not batch.span.is_recording()
        assert batch.span.get_span_context().is_valid  # a real id: a skill's spans stay in its unsampled trace
        assert not batch.span.get_span_context().trace_flags.sampled
        assert batch.start_span("phase") is batch.span
        recorder.end(batch)
        assert not batch.pending
    finally:
        recorder.deactivate()
        provider.shutdown()
    assert exporter.get_finished_spans() == ()


def test_without_an_sdk_tracer_ticks_use_the_apis_no_op_spans() -> None:
    recorder = TickRecorder(trace.NoOpTracerProvider())
    recorder.activate()
    try:
        assert not recorder.defers_spans
        first = recorder.begin()
        assert first.start_span("phase") is first.span
        assert not first.span.get_span_context().is_valid
        recorder.end(first)
        assert not first.spans
    finally:
        recorder.deactivate()


QUIET_RUN = """
import openral_observability.deferred as deferred
from openral_hal.testing import RecordingHAL
from openral_rskill.testing import ScriptedSkill
from openral_runner.hardware import HardwareRunner
from openral_world_state import WorldStateAggregator

def no_instrument(name, unit="ms"):
    raise AssertionError(f"a metric sample reached an instrument with nothing installed: {name}")

deferred.histogram = no_instrument
skill = ScriptedSkill(["j0"])
skill.configure()
skill.activate()
runner = HardwareRunner(hal=RecordingHAL(["j0"]), skill=skill, aggregator=WorldStateAggregator(), rate_hz=500.0)
runner.activate()
result = runner.run(50)
runner.deactivate()
print(type(runner._telemetry_recorder.begin()).__name__, result.n_ticks, result.withheld_actions)
"""


def test_with_nothing_installed_a_tick_records_nothing() -> None:
    """No SDK tracer or meter at activation: ticks skip every telemetry call, and the loop still runs."""
    import os  # noqa: PLC0415
    import subprocess  # noqa: PLC0415
    import sys  # noqa: PLC0415

    env = {k: v for k, v in os.environ.items() if not k.startswith("OTEL_")}
    proc = subprocess.run(
        [sys.executable, "-c", QUIET_RUN], env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr
    # The last line is the result; a late tick under load may log a warning before it.
    assert proc.stdout.strip().splitlines()[-1].split() == ["QuietTickTelemetry", "50", "0"]
