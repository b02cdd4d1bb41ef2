"""Telemetry names and helpers on the OpenTelemetry API; a no-op until an SDK is set up."""

from openral_observability import metrics, semconv
from openral_observability.tracing import trace_id_hex, traceparent, tracer

__all__ = ["metrics", "semconv", "trace_id_hex", "traceparent", "tracer"]
