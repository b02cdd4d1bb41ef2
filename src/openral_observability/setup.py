"""``setup()``: install the OpenTelemetry SDK and OTLP exporters for traces, metrics and logs.

This module imports the SDK and the exporters only inside ``setup()`` (as does the tick sampler
it installs), so importing it costs nothing and a missing ``otel`` extra surfaces only when
export is asked for. Library code never calls it; the CLI does, once, at start-up.

Configuration comes from the explicit arguments or, where they are ``None``, from the
standard variables: ``OTEL_EXPORTER_OTLP_ENDPOINT`` (or the per-signal
``OTEL_EXPORTER_OTLP_{TRACES,METRICS,LOGS}_ENDPOINT``), ``OTEL_EXPORTER_OTLP[_<SIGNAL>]_PROTOCOL``,
``OTEL_{TRACES,METRICS,LOGS}_EXPORTER`` (``otlp`` or ``none``), ``OTEL_TRACES_SAMPLER[_ARG]``,
``OTEL_SERVICE_NAME``, ``OTEL_RESOURCE_ATTRIBUTES``, ``OTEL_METRIC_EXPORT_INTERVAL`` and
``OTEL_SDK_DISABLED``. The exporters read the rest themselves (headers, timeout, TLS).
With no endpoint anywhere, nothing is installed and every span, metric and log stays a no-op.
"""

from __future__ import annotations

import atexit
import os
import threading
from collections.abc import Callable, Sequence
from importlib import metadata
from typing import TYPE_CHECKING, Any, Final, Protocol

import structlog
from opentelemetry import trace

from openral_core import ROSDependencyMissing, ROSRuntimeError
from openral_observability.sampling import tick_sampler
from openral_observability.semconv import METER_NAME, TRACER_NAME
from openral_observability.span_pipeline import SdkSpanPipeline
from openral_observability.telemetry_config import (
    DEFAULT_SERVICE_NAME,
    OTEL_EXTRA,
    PROTOCOL_GRPC,
    PROTOCOL_HTTP,
    PROTOCOLS,
    TelemetryConfig,
    resolve_config,
)
from openral_observability.telemetry_worker import InProcessSink, offload_to

if TYPE_CHECKING:
    from openral_observability.export_process import ExportProcess


MS_HISTOGRAM_BOUNDARIES: Final = (
    0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 25.0, 50.0, 100.0, 250.0, 500.0, 1000.0, 2500.0, 10000.0,
)  # fmt: skip
"""Bucket bounds (ms) for openral's duration histograms: tick phases live between 10 µs and a second."""

SPAN_QUEUE_SIZE: Final = 8192
"""Spans buffered for export: about two seconds of a 500 Hz deployment's ticks."""
SPAN_EXPORT_BATCH_SIZE: Final = 1024
"""Spans per OTLP request: fewer, larger requests cost the exporter thread less GIL time per span."""

_log = structlog.get_logger(__name__)


class _Provider(Protocol):
    """What the SDK's tracer, meter and logger providers share."""

    def force_flush(self, timeout_millis: int = ...) -> bool: ...

    def shutdown(self) -> None: ...


class Telemetry:
    """What ``setup()`` installed. ``shutdown()`` flushes and stops it; a no-op handle when nothing was.

    Usable as a context manager: leaving the block shuts down. Also registered with ``atexit``,
    so a process that forgets to shut down still flushes.
    """

    def __init__(
        self,
        config: TelemetryConfig | None = None,
        providers: Sequence[_Provider] = (),
        export_process: ExportProcess | None = None,
    ) -> None:
        self.config = config
        self._providers = tuple(providers)
        self.export_process = export_process
        self._lock = threading.Lock()
        self._done = not self._providers
        if not self._done:
            atexit.register(self.shutdown)

    @property
    def enabled(self) -> bool:
        """Whether an SDK was installed (and not yet shut down)."""
        return not self._done

    def force_flush(self, timeout_s: float = 5.0) -> bool:
        """Export everything buffered now; ``False`` when it did not finish within ``timeout_s``."""

        def flush() -> bool:
            flushed = self.export_process is None or self.export_process.force_flush(timeout_s)
            return all(p.force_flush(int(timeout_s * 1e3)) for p in self._providers) and flushed

        return self._bounded(flush, timeout_s)

    def shutdown(self, timeout_s: float = 5.0) -> bool:
        """Flush, then stop the exporters. Idempotent.

        Bounded by ``timeout_s``: an unreachable collector delays exit by at most that long,
        after which what is still buffered is dropped with a warning.

        Returns:
            ``True`` when everything was flushed and stopped in time.
        """
        with self._lock:
            if self._done:
                return True
            self._done = True
        atexit.unregister(self.shutdown)

        def flush_and_stop() -> bool:
            flushed = True
            if self.export_process is not None:
                offload_to(None)
                flushed = self.export_process.shutdown(timeout_s)
            flushed = all(p.force_flush(int(timeout_s * 1e3)) for p in self._providers) and flushed
            for provider in self._providers:
                provider.shutdown()
            return flushed

        return self._bounded(flush_and_stop, timeout_s)

    def _bounded(self, work: Callable[[], bool], timeout_s: float) -> bool:
        if not self._providers:
            return True
        outcome: list[bool] = []

        def target() -> None:
            try:
                outcome.append(work())
            except Exception as exc:  # an exporter failure must not turn a clean exit into a crash
                _log.warning("telemetry flush failed", error=str(exc))
                outcome.append(False)

        worker = threading.Thread(target=target, name="openral-otel-flush", daemon=True)
        worker.start()
        worker.join(timeout_s)
        if not outcome:
            _log.warning("telemetry flush timed out; buffered spans, metrics and logs dropped", timeout_s=timeout_s)
            return False
        return outcome[0]

    def __enter__(self) -> Telemetry:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.shutdown()


def setup(
    *,
    endpoint: str | None = None,
    protocol: str | None = None,
    sample_ratio: float | None = None,
    service_name: str = DEFAULT_SERVICE_NAME,
    metric_interval_ms: int | None = None,
    export_process: bool = True,
) -> Telemetry:
    """Install tracer, meter and logger providers exporting over OTLP, once per process.

    Traces go through a ``BatchSpanProcessor``, metrics through a
    ``PeriodicExportingMetricReader`` (duration histograms get millisecond buckets), and
    structlog events reach the ``LoggerProvider`` through
    :class:`openral_observability.logs.OTelLogBridge` with the current trace and span ids.

    With ``export_process`` (the default), the spans and histogram samples of runner ticks are
    exported by a child process (:mod:`openral_observability.export_process`), so OTLP encoding
    never competes with the tick thread for the interpreter lock.

    Args:
        endpoint / protocol / sample_ratio / service_name / metric_interval_ms: See :func:`resolve_config`.
        export_process: Export tick telemetry from a child process rather than from this one.

    Returns:
        A handle whose ``shutdown()`` flushes; a no-op handle when nothing is configured.

    Raises:
        ROSConfigError: Invalid settings (see :func:`resolve_config`).
        ROSDependencyMissing: Export was asked for but the ``otel`` extra is not installed.
        ROSRuntimeError: Another tracer provider is already installed in this process.
    """
    config = resolve_config(
        endpoint=endpoint,
        protocol=protocol,
        sample_ratio=sample_ratio,
        service_name=service_name,
        metric_interval_ms=metric_interval_ms,
    )
    if config is None:
        return Telemetry()
    if not isinstance(trace.get_tracer_provider(), trace.ProxyTracerProvider):
        raise ROSRuntimeError(
            "an OpenTelemetry tracer provider is already installed in this process; setup() installs its own once"
        )
    providers = install(config)
    process = None
    if export_process and ("traces" in config.endpoints or "metrics" in config.endpoints):
        from openral_observability.export_process import ExportProcess  # noqa: PLC0415

        pipeline = SdkSpanPipeline.of(trace.get_tracer_provider().get_tracer(TRACER_NAME))
        process = ExportProcess(config, fallback=InProcessSink(pipeline))
        offload_to(process)
    return Telemetry(config, providers, process)


def install(config: TelemetryConfig) -> list[_Provider]:
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
    providers: list[_Provider] = []

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


__all__ = [
    "OTEL_EXTRA",
    "PROTOCOLS",
    "PROTOCOL_GRPC",
    "PROTOCOL_HTTP",
    "Telemetry",
    "TelemetryConfig",
    "resolve_config",
    "setup",
    "tick_sampler",
]
