"""Installing the OpenTelemetry SDK's providers and OTLP exporters in this process.

Shared by ``setup()`` (the runner's process) and the telemetry export process, which installs the
same providers from the same configuration; neither imports the other for it. The SDK and the
exporters are imported inside :func:`install`, so importing this module costs nothing.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from importlib import metadata
from typing import Any, Final, Protocol

from opentelemetry import trace

from openral_core import ROSDependencyMissing
from openral_observability.sampling import tick_sampler
from openral_observability.semconv import METER_NAME
from openral_observability.telemetry_config import OTEL_EXTRA, PROTOCOL_GRPC, TelemetryConfig

MS_HISTOGRAM_BOUNDARIES: Final = (
    0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 25.0, 50.0, 100.0, 250.0, 500.0, 1000.0, 2500.0, 10000.0,
)  # fmt: skip
"""Bucket bounds (ms) for openral's duration histograms: tick phases live between 10 µs and a second."""

SPAN_QUEUE_SIZE: Final = 8192
"""Spans buffered for export: about two seconds of a 500 Hz deployment's ticks."""
SPAN_EXPORT_BATCH_SIZE: Final = 1024
"""Spans per OTLP request: fewer, larger requests cost the exporter thread less GIL time per span."""


class Provider(Protocol):
    """What the SDK's tracer, meter and logger providers share."""

    def force_flush(self, timeout_millis: int = ...) -> bool: ...

    def shutdown(self) -> None: ...


def install(config: TelemetryConfig) -> list[Provider]:
    """Install the SDK providers and OTLP exporters ``config`` asks for, globally in this process.

    Raises:
        ROSDependencyMissing: The ``otel`` extra is not installed.
    """
    try:
        from opentelemetry import _logs, metrics  # noqa: PLC0415
        from opentelemetry.sdk._logs import LoggerProvider  # noqa: PLC0415
        from opentelemetry.sdk._logs.export import BatchLogRecordProcessor  # noqa: PLC0415
        from opentelemetry.sdk.metrics import Histogram, MeterProvider  # noqa: PLC0415
        from opentelemetry.sdk.metrics.export import PeriodicExportingMetricReader  # noqa: PLC0415
        from opentelemetry.sdk.metrics.view import ExplicitBucketHistogramAggregation, View  # noqa: PLC0415
        from opentelemetry.sdk.resources import Resource  # noqa: PLC0415
        from opentelemetry.sdk.trace import TracerProvider  # noqa: PLC0415
        from opentelemetry.sdk.trace.export import BatchSpanProcessor  # noqa: PLC0415
    except ImportError as exc:
        raise ROSDependencyMissing(
            exc.name or "opentelemetry.sdk", extra=OTEL_EXTRA, needed_for="OpenTelemetry export"
        ) from exc
    exporters = _exporter_classes(config)

    attributes: dict[str, str] = {"service.version": _version()}
    if config.service_name is not None:
        attributes["service.name"] = config.service_name
    resource = Resource.create(attributes)
    providers: list[Provider] = []

    if "traces" in config.endpoints:
        ratio = config.sample_ratio
        if ratio is None and not os.environ.get("OTEL_TRACES_SAMPLER"):
            ratio = 1.0
        sampler = None if ratio is None else tick_sampler(ratio)
        tracer_provider = TracerProvider(resource=resource, sampler=sampler, shutdown_on_exit=False)
        # Spans leave the tick thread as soon as they end; encoding and posting happen on the
        # processor's thread in batches, which is what holds the GIL least per span.
        tracer_provider.add_span_processor(
            BatchSpanProcessor(
                exporters["traces"](config.endpoints["traces"]),
                max_queue_size=SPAN_QUEUE_SIZE,
                max_export_batch_size=SPAN_EXPORT_BATCH_SIZE,
            )
        )
        trace.set_tracer_provider(tracer_provider)
        providers.append(tracer_provider)
    if "metrics" in config.endpoints:
        reader = PeriodicExportingMetricReader(
            exporters["metrics"](config.endpoints["metrics"]), export_interval_millis=config.metric_interval_ms
        )
        ms_buckets = View(
            instrument_type=Histogram,
            instrument_unit="ms",
            meter_name=METER_NAME,
            aggregation=ExplicitBucketHistogramAggregation(MS_HISTOGRAM_BOUNDARIES),
        )
        meter_provider = MeterProvider(
            metric_readers=[reader], resource=resource, views=[ms_buckets], shutdown_on_exit=False
        )
        metrics.set_meter_provider(meter_provider)
        providers.append(meter_provider)
    if "logs" in config.endpoints:
        logger_provider = LoggerProvider(resource=resource, shutdown_on_exit=False)
        logger_provider.add_log_record_processor(BatchLogRecordProcessor(exporters["logs"](config.endpoints["logs"])))
        _logs.set_logger_provider(logger_provider)
        providers.append(logger_provider)
    return providers


def _exporter_classes(config: TelemetryConfig) -> dict[str, Callable[[str | None], Any]]:
    """Signal → exporter factory taking the endpoint, for the protocol chosen per signal."""
    factories: dict[str, Callable[[str | None], Any]] = {}
    for signal, protocol in config.protocols.items():
        try:
            factories[signal] = _exporter_factory(signal, protocol)
        except ImportError as exc:
            package = "grpc" if protocol == PROTOCOL_GRPC else "http"
            raise ROSDependencyMissing(
                exc.name or f"opentelemetry.exporter.otlp.proto.{package}",
                extra=OTEL_EXTRA,
                needed_for=f"OTLP/{protocol} export",
            ) from exc
    return factories


def _exporter_factory(signal: str, protocol: str) -> Callable[[str | None], Any]:
    if protocol == PROTOCOL_GRPC:
        if signal == "traces":
            from opentelemetry.exporter.otlp.proto.grpc.trace_exporter import OTLPSpanExporter  # noqa: PLC0415

            return lambda endpoint: OTLPSpanExporter(endpoint=endpoint)
        if signal == "metrics":
            from opentelemetry.exporter.otlp.proto.grpc.metric_exporter import OTLPMetricExporter  # noqa: PLC0415

            return lambda endpoint: OTLPMetricExporter(endpoint=endpoint)
        from opentelemetry.exporter.otlp.proto.grpc._log_exporter import OTLPLogExporter  # noqa: PLC0415

        return lambda endpoint: OTLPLogExporter(endpoint=endpoint)
    if signal == "traces":
        from opentelemetry.exporter.otlp.proto.http.trace_exporter import (  # noqa: PLC0415
            OTLPSpanExporter as HTTPSpanExporter,
        )

        return lambda endpoint: HTTPSpanExporter(endpoint=endpoint)
    if signal == "metrics":
        from opentelemetry.exporter.otlp.proto.http.metric_exporter import (  # noqa: PLC0415
            OTLPMetricExporter as HTTPMetricExporter,
        )

        return lambda endpoint: HTTPMetricExporter(endpoint=endpoint)
    from opentelemetry.exporter.otlp.proto.http._log_exporter import (  # noqa: PLC0415
        OTLPLogExporter as HTTPLogExporter,
    )

    return lambda endpoint: HTTPLogExporter(endpoint=endpoint)


def _version() -> str:
    try:
        return metadata.version("openral")
    except metadata.PackageNotFoundError:
        return "unknown"
