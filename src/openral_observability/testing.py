"""``OTLPReceiver``: a minimal OTLP/HTTP collector on the loopback interface, for tests and benchmarks.

It accepts ``POST /v1/traces``, ``/v1/metrics`` and ``/v1/logs`` (protobuf, optionally gzip),
decodes every request with the official ``opentelemetry-proto`` messages and keeps them.
Needs ``opentelemetry-proto`` (installed with the ``otel`` extra).
"""

from __future__ import annotations

import gzip
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from openral_core import ROSDependencyMissing

try:
    from opentelemetry.proto.collector.logs.v1.logs_service_pb2 import (
        ExportLogsServiceRequest,
        ExportLogsServiceResponse,
    )
    from opentelemetry.proto.collector.metrics.v1.metrics_service_pb2 import (
        ExportMetricsServiceRequest,
        ExportMetricsServiceResponse,
    )
    from opentelemetry.proto.collector.trace.v1.trace_service_pb2 import (
        ExportTraceServiceRequest,
        ExportTraceServiceResponse,
    )
    from opentelemetry.proto.logs.v1.logs_pb2 import LogRecord
    from opentelemetry.proto.metrics.v1.metrics_pb2 import Metric
    from opentelemetry.proto.trace.v1.trace_pb2 import Span
except ImportError as exc:
    raise ROSDependencyMissing(
        exc.name or "opentelemetry.proto", extra="otel", needed_for="the OTLP test receiver"
    ) from exc

_MESSAGES: dict[str, tuple[type[Any], bytes]] = {
    "/v1/traces": (ExportTraceServiceRequest, ExportTraceServiceResponse().SerializeToString()),
    "/v1/metrics": (ExportMetricsServiceRequest, ExportMetricsServiceResponse().SerializeToString()),
    "/v1/logs": (ExportLogsServiceRequest, ExportLogsServiceResponse().SerializeToString()),
}


class OTLPReceiver:
    """Receives OTLP/HTTP exports on ``127.0.0.1`` at an ephemeral port.

    Args:
        decode: Parse and keep each request; with ``False`` only requests and bytes are counted.

    Attributes:
        requests: Requests received per path.
        bytes_received: Request body bytes received in total (after decompression).
    """

    def __init__(self, *, decode: bool = True) -> None:
        self.decode = decode
        self.requests: dict[str, int] = {}
        self.bytes_received = 0
        self._traces: list[ExportTraceServiceRequest] = []
        self._metrics: list[ExportMetricsServiceRequest] = []
        self._logs: list[ExportLogsServiceRequest] = []
        self._lock = threading.Lock()
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), self._handler_class())
        self._server.daemon_threads = True
        self._thread: threading.Thread | None = None

    @property
    def endpoint(self) -> str:
        """Base URL to give an exporter (``--otlp-endpoint``)."""
        return f"http://127.0.0.1:{self._server.server_address[1]}"

    def start(self) -> OTLPReceiver:
        """Serve on a background thread. Idempotent."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._server.serve_forever, name="otlp-receiver", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the socket."""
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join(timeout=5.0)
            self._thread = None
        self._server.server_close()

    def __enter__(self) -> OTLPReceiver:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    def spans(self) -> list[Span]:
        """Every span received so far, in arrival order."""
        with self._lock:
            requests = list(self._traces)
        return [span for r in requests for rs in r.resource_spans for ss in rs.scope_spans for span in ss.spans]

    def metrics(self) -> list[Metric]:
        """Every metric received so far (one entry per metric per export)."""
        with self._lock:
            requests = list(self._metrics)
        return [m for r in requests for rm in r.resource_metrics for sm in rm.scope_metrics for m in sm.metrics]

    def logs(self) -> list[LogRecord]:
        """Every log record received so far."""
        with self._lock:
            requests = list(self._logs)
        return [lr for r in requests for rl in r.resource_logs for sl in rl.scope_logs for lr in sl.log_records]

    def resource_attributes(self) -> dict[str, str]:
        """String attributes of the first exported resource (``service.name`` ...)."""
        with self._lock:
            requests = list(self._traces)
        for request in requests:
            for rs in request.resource_spans:
                return {kv.key: kv.value.string_value for kv in rs.resource.attributes}
        return {}

    def wait_for(self, predicate: Callable[[OTLPReceiver], bool], timeout_s: float = 10.0) -> bool:
        """Poll ``predicate(self)`` until it holds or ``timeout_s`` passes; returns its last value."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate(self):
                return True
            time.sleep(0.02)
        return predicate(self)

    def _store(self, path: str, body: bytes) -> bytes | None:
        entry = _MESSAGES.get(path)
        if entry is None:
            return None
        message_type, response = entry
        with self._lock:
            self.requests[path] = self.requests.get(path, 0) + 1
            self.bytes_received += len(body)
        if not self.decode:
            return response
        message = message_type.FromString(body)
        with self._lock:
            if isinstance(message, ExportTraceServiceRequest):
                self._traces.append(message)
            elif isinstance(message, ExportMetricsServiceRequest):
                self._metrics.append(message)
            else:
                self._logs.append(message)
        return response

    def _handler_class(self) -> type[BaseHTTPRequestHandler]:
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", "0")))
                if self.headers.get("Content-Encoding", "") == "gzip":
                    body = gzip.decompress(body)
                response = receiver._store(self.path, body)
                if response is None:
                    self.send_error(404)
                    return
                self.send_response(200)
                self.send_header("Content-Type", "application/x-protobuf")
                self.send_header("Content-Length", str(len(response)))
                self.end_headers()
                self.wfile.write(response)

            def log_message(self, format: str, *args: Any) -> None:
                """Silence the per-request access log."""

        return Handler


__all__ = ["OTLPReceiver"]
