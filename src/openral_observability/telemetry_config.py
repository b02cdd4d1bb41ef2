"""Telemetry configuration: what ``setup()`` installs, resolved once from arguments and ``OTEL_*`` variables."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from openral_core import ROSConfigError

PROTOCOL_HTTP: Final = "http/protobuf"
PROTOCOL_GRPC: Final = "grpc"
PROTOCOLS: Final = (PROTOCOL_HTTP, PROTOCOL_GRPC)
SIGNALS: Final = ("traces", "metrics", "logs")
OTEL_EXTRA: Final = "otel"
DEFAULT_SERVICE_NAME: Final = "openral"


@dataclass(frozen=True)
class TelemetryConfig:
    """What ``setup()`` will install, resolved from arguments and the environment.

    Attributes:
        endpoints: Signal (``traces``, ``metrics``, ``logs``) → full exporter URL, or ``None``
            to let the exporter read its own ``OTEL_EXPORTER_OTLP_*`` variables. Signals not
            listed are not exported.
        protocols: Signal → ``http/protobuf`` or ``grpc``.
        sample_ratio: Fraction of ticks traced (see :func:`tick_sampler`); ``None`` keeps
            ``OTEL_TRACES_SAMPLER`` when set, else every tick is traced.
        service_name: ``service.name`` resource attribute, ``None`` when the environment sets it.
        metric_interval_ms: Export period of the metric reader; ``None`` for the SDK default.
    """

    endpoints: Mapping[str, str | None]
    protocols: Mapping[str, str]
    sample_ratio: float | None = None
    service_name: str | None = DEFAULT_SERVICE_NAME
    metric_interval_ms: int | None = None


def resolve_config(
    *,
    endpoint: str | None = None,
    protocol: str | None = None,
    sample_ratio: float | None = None,
    service_name: str = DEFAULT_SERVICE_NAME,
    metric_interval_ms: int | None = None,
    env: Mapping[str, str] | None = None,
) -> TelemetryConfig | None:
    """Decide what to export; ``None`` when nothing is configured (or ``OTEL_SDK_DISABLED=true``).

    Args:
        endpoint: Collector base URL (``http://host:4318`` for HTTP, ``http://host:4317`` for gRPC);
            overrides every ``OTEL_EXPORTER_OTLP_*ENDPOINT`` variable.
        protocol: ``http/protobuf`` or ``grpc``; overrides ``OTEL_EXPORTER_OTLP_*PROTOCOL``.
        sample_ratio: In [0, 1]; fraction of ticks traced (see :func:`tick_sampler`).
        service_name: Used unless ``OTEL_SERVICE_NAME`` or ``OTEL_RESOURCE_ATTRIBUTES`` names the service.
        metric_interval_ms: Metric export period.
        env: The environment to read (``os.environ`` by default).

    Raises:
        ROSConfigError: Unknown protocol or exporter name, or a ratio outside [0, 1].
    """
    env = os.environ if env is None else env
    if env.get("OTEL_SDK_DISABLED", "").strip().lower() == "true":
        return None
    if sample_ratio is not None and not 0.0 <= sample_ratio <= 1.0:
        raise ROSConfigError(f"must be within [0, 1], got {sample_ratio}", field="trace_sample_ratio")
    if metric_interval_ms is not None and metric_interval_ms <= 0:
        raise ROSConfigError(f"must be positive, got {metric_interval_ms}", field="metric_interval_ms")
    endpoints: dict[str, str | None] = {}
    protocols: dict[str, str] = {}
    for signal in SIGNALS:
        exporter = env.get(f"OTEL_{signal.upper()}_EXPORTER", "otlp").strip().lower() or "otlp"
        if exporter == "none":
            continue
        if exporter != "otlp":
            raise ROSConfigError(
                f"exporter '{exporter}' is not supported",
                field=f"OTEL_{signal.upper()}_EXPORTER",
                hint="use otlp (the default) or none",
            )
        proto = (
            protocol
            or env.get(f"OTEL_EXPORTER_OTLP_{signal.upper()}_PROTOCOL")
            or env.get("OTEL_EXPORTER_OTLP_PROTOCOL")
            or PROTOCOL_HTTP
        ).strip()
        if proto not in PROTOCOLS:
            raise ROSConfigError(
                f"OTLP protocol '{proto}' is not supported",
                field="otlp_protocol",
                hint=f"use one of: {', '.join(PROTOCOLS)}",
            )
        if endpoint:
            endpoints[signal] = _signal_url(endpoint, signal, proto)
        elif env.get(f"OTEL_EXPORTER_OTLP_{signal.upper()}_ENDPOINT") or env.get("OTEL_EXPORTER_OTLP_ENDPOINT"):
            endpoints[signal] = None  # the exporter reads the variable itself, with its per-signal path rules
        else:
            continue
        protocols[signal] = proto
    if not endpoints:
        return None
    named_in_env = bool(env.get("OTEL_SERVICE_NAME")) or "service.name=" in env.get("OTEL_RESOURCE_ATTRIBUTES", "")
    return TelemetryConfig(
        endpoints=endpoints,
        protocols=protocols,
        sample_ratio=sample_ratio,
        service_name=None if named_in_env else service_name,
        metric_interval_ms=metric_interval_ms,
    )


def _signal_url(endpoint: str, signal: str, protocol: str) -> str:
    """HTTP exporters given an explicit URL post to it as is, so add the signal path; gRPC takes host:port."""
    if protocol == PROTOCOL_GRPC:
        return endpoint
    return f"{endpoint.rstrip('/')}/v1/{signal}"
