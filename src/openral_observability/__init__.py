"""Telemetry names and helpers on the OpenTelemetry API; a no-op until ``openral_observability.setup.setup()`` runs."""

from openral_observability import metrics, propagation, semconv
from openral_observability.propagation import current_traceparent
from openral_observability.tracing import record_error, trace_id_hex, traceparent, tracer

__all__ = [
    "current_traceparent",
    "metrics",
    "propagation",
    "record_error",
    "semconv",
    "trace_id_hex",
    "traceparent",
    "tracer",
]
