"""structlog → OpenTelemetry: trace ids on log lines and log records in the current span."""

from __future__ import annotations

from typing import Any

from opentelemetry import trace
from opentelemetry._logs import SeverityNumber
from opentelemetry.sdk._logs import LoggerProvider
from opentelemetry.sdk._logs.export import InMemoryLogRecordExporter, SimpleLogRecordProcessor

from openral_observability.logs import OTelLogBridge, add_trace_ids


def test_trace_ids_are_added_inside_a_span_only(telemetry: Any) -> None:
    assert add_trace_ids(None, "info", {"event": "x"}) == {"event": "x"}
    with trace.get_tracer("t").start_as_current_span("work") as span:
        ctx = span.get_span_context()
        out = add_trace_ids(None, "info", {"event": "x"})
    assert out == {"event": "x", "trace_id": f"{ctx.trace_id:032x}", "span_id": f"{ctx.span_id:016x}"}


def test_bridge_emits_a_record_in_the_current_span_and_passes_the_event_on(telemetry: Any) -> None:
    exporter = InMemoryLogRecordExporter()
    provider = LoggerProvider()
    provider.add_log_record_processor(SimpleLogRecordProcessor(exporter))
    bridge = OTelLogBridge(logger_provider=provider)
    with trace.get_tracer("t").start_as_current_span("work") as span:
        event = {"event": "tick late", "level": "warning", "lateness_ms": 1.5, "ids": [1, 2], "timestamp": "now"}
        assert bridge(None, "warning", dict(event)) == event
    (record,) = (r.log_record for r in exporter.get_finished_logs())
    assert record.body == "tick late"
    assert record.severity_number is SeverityNumber.WARN
    assert record.severity_text == "WARN"
    assert dict(record.attributes or {}) == {"lateness_ms": 1.5, "ids": "[1, 2]"}
    ctx = span.get_span_context()
    assert (record.trace_id, record.span_id) == (ctx.trace_id, ctx.span_id)
    provider.shutdown()


def test_bridge_without_a_provider_is_a_no_op() -> None:
    assert OTelLogBridge()(None, "info", {"event": "hello"}) == {"event": "hello"}
