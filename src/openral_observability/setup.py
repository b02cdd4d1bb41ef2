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
import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import structlog
from opentelemetry import trace

from openral_core import ROSRuntimeError
from openral_observability.sampling import tick_sampler
from openral_observability.sdk_install import MS_HISTOGRAM_BOUNDARIES, Provider, install
from openral_observability.semconv import TRACER_NAME
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


_log = structlog.get_logger(__name__)


class Telemetry:
    """What ``setup()`` installed. ``shutdown()`` flushes and stops it; a no-op handle when nothing was.

    Usable as a context manager: leaving the block shuts down. Also registered with ``atexit``,
    so a process that forgets to shut down still flushes.
    """

    def __init__(
        self,
        config: TelemetryConfig | None = None,
        providers: Sequence[Provider] = (),
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
        after which what is still buffered is dropped with a warning. An export process still
        starting is waited for first, within its start-up allowance
        (:meth:`~openral_observability.export_process.ExportProcess.wait_ready`).

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

        if self.export_process is not None:
            self.export_process.wait_ready()  # its start-up is not the collector's: outside the bound
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


__all__ = [
    "MS_HISTOGRAM_BOUNDARIES",
    "OTEL_EXTRA",
    "PROTOCOLS",
    "PROTOCOL_GRPC",
    "PROTOCOL_HTTP",
    "Telemetry",
    "TelemetryConfig",
    "install",
    "resolve_config",
    "setup",
    "tick_sampler",
]
