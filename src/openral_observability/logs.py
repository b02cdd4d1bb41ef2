"""structlog → OpenTelemetry: trace ids on every log line, and each event as an OTel log record.

Both are structlog processors on the OpenTelemetry API only. Until ``setup()`` installs a
``LoggerProvider`` the bridge hands records to the API's no-op logger, and outside a
recording span no ids are added, so the processors can always be configured.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, MutableMapping
from typing import Any, Final

from opentelemetry import _logs, trace
from opentelemetry._logs import LogRecord, SeverityNumber
from opentelemetry.util.types import AttributeValue

from openral_observability.semconv import LOG_SPAN_ID, LOG_TRACE_ID, TRACER_NAME

_SEVERITY: Final[Mapping[str, tuple[SeverityNumber, str]]] = {
    "debug": (SeverityNumber.DEBUG, "DEBUG"),
    "info": (SeverityNumber.INFO, "INFO"),
    "warning": (SeverityNumber.WARN, "WARN"),
    "warn": (SeverityNumber.WARN, "WARN"),
    "error": (SeverityNumber.ERROR, "ERROR"),
    "exception": (SeverityNumber.ERROR, "ERROR"),
    "critical": (SeverityNumber.FATAL, "FATAL"),
}
_NOT_ATTRIBUTES: Final = frozenset({"event", "level", "timestamp", LOG_TRACE_ID, LOG_SPAN_ID})


def add_trace_ids(_logger: Any, _method: str, event_dict: MutableMapping[str, Any]) -> MutableMapping[str, Any]:
    """structlog processor: add ``trace_id`` (32 hex) and ``span_id`` (16 hex) of the current span, if any."""
    span_context = trace.get_current_span().get_span_context()
    if span_context.is_valid:
        event_dict[LOG_TRACE_ID] = f"{span_context.trace_id:032x}"
        event_dict[LOG_SPAN_ID] = f"{span_context.span_id:016x}"
    return event_dict


class OTelLogBridge:
    """structlog processor: emit each event as an OpenTelemetry log record, then pass it on unchanged.

    The record's body is the event text, its severity the structlog level, its attributes
    the other keys (non-primitive values as text), and its trace and span ids those of the
    span current when the line was logged.

    Args:
        name: Instrumentation scope of the records.
        logger_provider: Where records go; the global provider (installed by ``setup()``) when ``None``.
    """

    def __init__(self, name: str = TRACER_NAME, logger_provider: _logs.LoggerProvider | None = None) -> None:
        self._logger = _logs.get_logger(name, logger_provider=logger_provider)

    def __call__(self, _logger: Any, method: str, event_dict: MutableMapping[str, Any]) -> MutableMapping[str, Any]:
        level = str(event_dict.get("level", method)).lower()
        number, text = _SEVERITY.get(level, (SeverityNumber.INFO, level.upper()))
        attributes = {key: _attribute(value) for key, value in event_dict.items() if key not in _NOT_ATTRIBUTES}
        # Ids passed explicitly rather than as a context: accepted by every opentelemetry-api from 1.25 on.
        span_context = trace.get_current_span().get_span_context()
        self._logger.emit(
            LogRecord(
                timestamp=time.time_ns(),
                trace_id=span_context.trace_id,
                span_id=span_context.span_id,
                trace_flags=span_context.trace_flags,
                severity_number=number,
                severity_text=text,
                body=str(event_dict.get("event", "")),
                attributes=attributes,
            )
        )
        return event_dict


def _attribute(value: Any) -> AttributeValue:
    if isinstance(value, str | bool | int | float):
        return value
    return str(value)


__all__ = ["OTelLogBridge", "add_trace_ids"]
