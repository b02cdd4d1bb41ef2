"""setup(): nothing installed until an endpoint is configured; then traces, metrics and logs reach a collector."""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent import futures
from typing import Any

import grpc
import pytest
from opentelemetry import _logs, metrics, trace
from opentelemetry.proto.collector.trace.v1 import trace_service_pb2, trace_service_pb2_grpc

from openral_core import ROSRuntimeError
from openral_observability.setup import PROTOCOL_GRPC, setup
from openral_observability.testing import OTLPReceiver

HTTP = "http://collector:4318"


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """The process environment without any OTEL_* variable, for this test."""
    for key in list(os.environ):
        if key.startswith("OTEL_"):
            monkeypatch.delenv(key)


def run_python(code: str, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    base = {k: v for k, v in os.environ.items() if not k.startswith("OTEL_")}
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        env={**base, **(env or {})},
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.mark.usefixtures("clean_env")
def test_setup_with_nothing_configured_installs_nothing() -> None:
    before = (trace.get_tracer_provider(), metrics.get_meter_provider(), _logs.get_logger_provider())
    handle = setup(protocol=PROTOCOL_GRPC, sample_ratio=0.5)
    assert not handle.enabled
    assert handle.config is None
    assert (trace.get_tracer_provider(), metrics.get_meter_provider(), _logs.get_logger_provider()) == before
    assert handle.force_flush()
    assert handle.shutdown()
    with handle:
        pass


def test_importing_setup_loads_no_sdk() -> None:
    code = "import sys, openral_observability.setup; print('opentelemetry.sdk' in sys.modules)"
    assert run_python(code).stdout.strip() == "False"


def test_setup_in_a_bare_process_is_a_no_op_and_ticks_carry_no_trace() -> None:
    code = (
        "from openral_observability.setup import setup\n"
        "from openral_observability import current_traceparent, tracer\n"
        "h = setup()\n"
        "with tracer().start_as_current_span('x'):\n"
        "    print(h.enabled, current_traceparent())\n"
    )
    proc = run_python(code)
    assert proc.stdout.split() == ["False", "None"], proc.stderr


# --- export ---------------------------------------------------------------------------------------

EXPORT = r"""
import sys, structlog
from openral_observability import metrics, semconv, tracer
from openral_observability.logs import OTelLogBridge, add_trace_ids
from openral_observability.setup import setup

structlog.configure(processors=[add_trace_ids, OTelLogBridge(), structlog.processors.KeyValueRenderer()],
                    logger_factory=structlog.PrintLoggerFactory(file=sys.stderr))
args = dict(arg.split("=", 1) for arg in sys.argv[1:])
handle = setup(endpoint=args.get("endpoint"), protocol=args.get("protocol"),
               sample_ratio=float(args["ratio"]) if "ratio" in args else None)
with tracer().start_as_current_span("outer") as span:
    structlog.get_logger().warning("inside", answer=42)
    metrics.record_histogram_ms(semconv.METRIC_TICK_DURATION, 1.5, {semconv.ATTR_SKILL_ID: "probe"})
ctx = span.get_span_context()
print(f"{ctx.trace_id:032x} {ctx.span_id:016x}")
print(handle.shutdown(timeout_s=30))  # returns once flushed; the room is for a loaded machine
"""


def test_http_export_of_traces_metrics_and_logs_with_trace_ids() -> None:
    with OTLPReceiver() as receiver:
        proc = run_python(EXPORT, f"endpoint={receiver.endpoint}")
        assert proc.returncode == 0, proc.stderr
        trace_id, span_id, flushed = proc.stdout.split()
        assert flushed == "True"
        (outer,) = receiver.spans()
        assert outer.name == "outer"
        assert (outer.trace_id.hex(), outer.span_id.hex()) == (trace_id, span_id)
        assert receiver.resource_attributes()["service.name"] == "openral"
        tick = [m for m in receiver.metrics() if m.name == "openral.tick.duration"]
        assert tick
        point = tick[-1].histogram.data_points[0]
        assert point.count == 1
        assert point.sum == 1.5
        assert 0.01 in point.explicit_bounds  # millisecond buckets, not the SDK's default
        (log,) = receiver.logs()
        assert log.body.string_value == "inside"
        assert log.severity_text == "WARN"
        assert (log.trace_id.hex(), log.span_id.hex()) == (trace_id, span_id)
        assert {kv.key: kv.value.int_value for kv in log.attributes}["answer"] == 42


def test_environment_configures_export_and_a_zero_ratio_samples_nothing() -> None:
    with OTLPReceiver() as receiver:
        env = {"OTEL_EXPORTER_OTLP_ENDPOINT": receiver.endpoint, "OTEL_SERVICE_NAME": "arm-7"}
        proc = run_python(EXPORT, "ratio=0", env=env)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.split()[-1] == "True", proc.stdout + proc.stderr  # everything flushed
        assert receiver.spans() == []
        assert any(m.name == "openral.tick.duration" for m in receiver.metrics())  # metrics are not sampled
        proc = run_python(EXPORT, env=env)
        assert proc.returncode == 0, proc.stderr
        assert [s.name for s in receiver.spans()] == ["outer"]
        assert receiver.resource_attributes()["service.name"] == "arm-7"


def test_grpc_export() -> None:
    received: list[Any] = []

    class Traces(trace_service_pb2_grpc.TraceServiceServicer):
        def Export(self, request: Any, context: Any) -> Any:
            received.append(request)
            return trace_service_pb2.ExportTraceServiceResponse()

    server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
    trace_service_pb2_grpc.add_TraceServiceServicer_to_server(Traces(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        env = {"OTEL_METRICS_EXPORTER": "none", "OTEL_LOGS_EXPORTER": "none"}
        proc = run_python(EXPORT, f"endpoint=http://127.0.0.1:{port}", "protocol=grpc", env=env)
        assert proc.returncode == 0, proc.stderr
    finally:
        server.stop(grace=None)
    names = [s.name for r in received for rs in r.resource_spans for ss in rs.scope_spans for s in ss.spans]
    assert names == ["outer"]


def test_missing_extra_names_it() -> None:
    code = (
        "import sys\n"
        "sys.modules['opentelemetry.sdk'] = None\n"
        "from openral_core import ROSDependencyMissing\n"
        "from openral_observability.setup import setup\n"
        "try:\n"
        "    setup(endpoint='http://127.0.0.1:9')\n"
        "except ROSDependencyMissing as exc:\n"
        "    print(exc.extra, '|', exc)\n"
    )
    proc = run_python(code)
    assert proc.stdout.startswith("otel |"), proc.stderr
    assert "openral[otel]" in proc.stdout


def test_a_second_provider_is_refused(otel: Any) -> None:
    with pytest.raises(ROSRuntimeError, match="already installed"):
        setup(endpoint="http://127.0.0.1:9")


def test_shutdown_is_bounded_when_the_collector_is_down() -> None:
    code = (
        "import time\n"
        "from openral_observability import tracer\n"
        "from openral_observability.setup import setup\n"
        "h = setup(endpoint='http://127.0.0.1:9')\n"
        "tracer().start_span('lost').end()\n"
        "assert h.export_process.wait_ready()\n"  # its start-up is waited for outside the bound
        "t = time.monotonic(); ok = h.shutdown(timeout_s=0.5)\n"
        "print(ok, round(time.monotonic() - t, 1))\n"
    )
    proc = run_python(code)
    ok, took = proc.stdout.splitlines()[-1].split()  # unconfigured structlog warns on stdout first
    assert ok == "False"
    assert "timed out" in proc.stdout
    assert float(took) < 5.0  # the 0.5 s asked for; the exporter's own retries would take 10 s or more
