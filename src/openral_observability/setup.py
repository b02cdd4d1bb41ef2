"""``setup()``: install the OpenTelemetry SDK and OTLP exporters for traces, metrics and logs.

This is the only module that imports the SDK and the exporters, and it does so only inside
``setup()``, so importing it costs nothing and a missing ``otel`` extra surfaces only when
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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from typing import TYPE_CHECKING, Any, Final, Protocol

import structlog
from opentelemetry import trace

from openral_core import ROSConfigError, ROSDependencyMissing, ROSRuntimeError
from openral_observability.semconv import METER_NAME, SPAN_TICK, TRACER_NAME
from openral_observability.span_pipeline import SdkSpanPipeline
from openral_observability.telemetry_worker import InProcessSink, offload_to

if TYPE_CHECKING:
    from openral_observability.export_process import ExportProcess

PROTOCOL_HTTP: Final = "http/protobuf"
PROTOCOL_GRPC: Final = "grpc"
PROTOCOLS: Final = (PROTOCOL_HTTP, PROTOCOL_GRPC)
SIGNALS: Final = ("traces", "metrics", "logs")
OTEL_EXTRA: Final = "otel"
DEFAULT_SERVICE_NAME: Final = "openral"

MS_HISTOGRAM_BOUNDARIES: Final = (
    0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 25.0, 50.0, 100.0, 250.0, 500.0, 1000.0, 2500.0, 10000.0,
)  # fmt: skip
"""Bucket bounds (ms) for openral's duration histograms: tick phases live between 10 µs and a second."""

SPAN_QUEUE_SIZE: Final = 8192
"""Spans buffered for export: about two seconds of a 500 Hz deployment's ticks."""
SPAN_EXPORT_BATCH_SIZE: Final = 1024
"""Spans per OTLP request: fewer, larger requests cost the exporter thread less GIL time per span."""

_log = structlog.get_logger(__name__)


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


def tick_sampler(ratio: float) -> Any:
    """A sampler that traces ``ratio`` of the ticks, each tick whole, independently of its parent.

    * ``rskill.tick`` spans: every ``1/ratio``-th tick is recorded (a deterministic credit
      counter, so ``0.1`` traces exactly one tick in ten), whether or not the enclosing span
      (``cli.command``) is, and whatever the trace id: all ticks of one deployment share the
      ``cli.command`` trace, so a trace-id ratio would keep all of them or none.
    * Any other span with a parent follows the parent: a traced tick is traced with all its
      phase spans, an untraced tick costs only non-recording spans.
    * Other root spans (``cli.command``) are recorded unless ``ratio`` is 0, so traced ticks
      always have their parent.

    A ratio of 1 records everything, like the SDK's default, with a cheaper decision per span.

    Raises:
        ROSDependencyMissing: The ``otel`` extra is not installed.
    """
    try:
        from opentelemetry.sdk.trace.sampling import Decision, Sampler, SamplingResult  # noqa: PLC0415
    except ImportError as exc:
        raise ROSDependencyMissing(exc.name or "opentelemetry.sdk", extra=OTEL_EXTRA, needed_for="sampling") from exc

    record = SamplingResult(Decision.RECORD_AND_SAMPLE)
    drop = SamplingResult(Decision.DROP)

    class TickSampler(Sampler):
        def __init__(self) -> None:
            self._credit = 1.0 - ratio if ratio > 0.0 else 0.0  # the first tick is traced unless ratio is 0

        def should_sample(  # noqa: PLR0917  (the SDK's signature)
            self,
            parent_context: Any,
            trace_id: int,
            name: str,
            kind: Any = None,
            attributes: Any = None,
            links: Any = None,
            trace_state: Any = None,
        ) -> Any:
            parent = trace.get_current_span(parent_context).get_span_context()
            if name == SPAN_TICK:
                self._credit += ratio
                if self._credit >= 1.0:
                    self._credit -= 1.0
                    sampled = True
                else:
                    sampled = False
            elif parent.is_valid:
                sampled = parent.trace_flags.sampled
            else:
                sampled = ratio > 0.0
            state = parent.trace_state if parent.is_valid else None
            if not sampled:
                return SamplingResult(Decision.DROP, None, state) if state else drop
            if not state and not attributes:
                return record
            # The SDK takes the span's start attributes from the sampling result.
            return SamplingResult(Decision.RECORD_AND_SAMPLE, attributes, state)

        def get_description(self) -> str:
            return f"OpenRALTickSampler{{{ratio}}}"

    return TickSampler()


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
