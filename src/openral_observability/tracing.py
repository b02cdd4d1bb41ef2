"""Span helpers on the OpenTelemetry API. No SDK here: until ``setup()`` installs one, spans are no-ops."""

from __future__ import annotations

from opentelemetry import trace
from opentelemetry.trace import Span, Status, StatusCode, Tracer

from openral_observability.semconv import TRACER_NAME


def tracer() -> Tracer:
    """The openral tracer from the current global provider.

    Looked up per call site rather than cached at import, so a provider installed later
    (``setup()`` or a test's in-memory exporter) is honoured.
    """
    return trace.get_tracer(TRACER_NAME)


def traceparent(span: Span) -> str | None:
    """The W3C ``traceparent`` header value of ``span``, or ``None`` for an invalid (no-op) span."""
    ctx = span.get_span_context()
    if not ctx.is_valid:
        return None
    return f"00-{ctx.trace_id:032x}-{ctx.span_id:016x}-{int(ctx.trace_flags):02x}"


def trace_id_hex(span: Span) -> str | None:
    """The 32-hex trace id of ``span``, or ``None`` when tracing is off."""
    ctx = span.get_span_context()
    return f"{ctx.trace_id:032x}" if ctx.is_valid else None


def record_error(span: Span, exc: BaseException) -> None:
    """Mark ``span`` failed with ``exc``: the exception as an event, and an error status carrying its message."""
    span.record_exception(exc)
    span.set_status(Status(StatusCode.ERROR, str(exc)))
