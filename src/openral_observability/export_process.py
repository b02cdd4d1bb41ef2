"""An export process for a runner's per-tick telemetry: OTLP encoding and posting off the interpreter lock.

Turning a span into OTLP protobuf and posting it costs the exporting thread about 50 µs of
Python per span. A 500 Hz tick makes seven spans and eight histogram samples, so that is
several hundred microseconds per tick, under the lock the tick thread needs. ``setup()``
therefore starts this module as a child process (``python -m openral_observability.export_process``)
with the same configuration. The runner's telemetry worker sends it each tick's spans and metric
samples as plain records over a pipe (pickled, length-prefixed); the child hands them to its own
SDK span processors and histograms, which export over OTLP exactly as the parent would. Spans
and metrics the parent makes outside ticks (``cli.command``, counters, logs) are exported by the
parent as usual; both processes carry the same resource.

Protocol on the child's stdin: a 4-byte little-endian length, then a pickled message:
``("data", spans, samples)`` or ``("flush",)``. On stdout the child writes one byte once its
exporters are installed (it is *ready*), and one byte per flush once its exporters have flushed.
End of input means shut down: the child flushes and exits, within ``flush_timeout_s`` whatever
the collector does. A child still starting when the parent shuts down (importing the SDK takes a
second or more, far longer on a machine short of cores) is waited for up to
:data:`STARTUP_ALLOWANCE_S` first, so a short run does not lose its telemetry to the child's
start-up. It ignores SIGINT and SIGTERM, so
a Ctrl-C or a service stop delivered to the whole process group still lets the parent's shutdown
drain it, and it never outlives the parent: the kernel kills it when the parent dies (Linux's
parent-death signal), even by SIGKILL. Once ready it runs at a lower priority (nice +10) than the
runner: on a machine short of cores, the tick thread gets the CPU first. It starts at the runner's
priority, so that its one-off start-up is not starved.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from typing import IO, Final

import structlog
from opentelemetry import trace

from openral_observability.deferred import MetricSample
from openral_observability.sdk_install import install
from openral_observability.semconv import TRACER_NAME
from openral_observability.span_pipeline import SdkSpanPipeline, SpanRecord
from openral_observability.telemetry_config import TelemetryConfig
from openral_observability.telemetry_worker import InProcessSink, TelemetrySink

_log = structlog.get_logger(__name__)

_HEADER: Final = struct.Struct("<I")
_FLUSHED: Final = b"\x01"
_READY: Final = b"\x02"
STARTUP_ALLOWANCE_S: Final = 30.0
"""How long after its start the child is waited for to become ready: its start-up is this
machine's cost, not the collector's, so it does not count against a flush's bound."""
SEND_INTERVAL_S: Final = 0.02
"""Records are sent at most this often (or when :data:`SEND_RECORDS` are buffered): one pickle and one
write per batch of ticks, not per tick."""
SEND_RECORDS: Final = 512


class ExportProcess:
    """The parent's end: buffers tick records and sends them to the child whenever the worker's queue empties.

    Thread-safe: every runner's telemetry worker may call it. If the child dies (or cannot
    start), records go to ``fallback``, with one warning; without a fallback they are dropped
    and counted in :attr:`dropped_spans` and :attr:`dropped_samples`.

    Args:
        config: What the child installs (its ``logs`` signal is left to the parent).
        fallback: Where records go when the child is gone: this process's own exporters.
    """

    def __init__(
        self, config: TelemetryConfig, fallback: TelemetrySink | None = None, *, flush_timeout_s: float = 5.0
    ) -> None:
        self._fallback = fallback
        settings = json.dumps(asdict(config))
        # The parent-death signal fires when the creating *thread* exits: create this on a thread
        # that lives as long as the runner (the CLI creates it on the main thread).
        self._process = subprocess.Popen(
            [sys.executable, "-m", __name__, settings, str(os.getpid()), repr(flush_timeout_s)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=os.environ.copy(),
        )
        self._started_at = time.monotonic()
        self._ready = False
        self._lock = threading.Lock()
        self._spans: list[SpanRecord] = []
        self._samples: list[MetricSample] = []
        self._alive = True
        self._sent_at = 0.0
        self.dropped_spans = 0
        self.dropped_samples = 0

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self._process.pid

    @property
    def running(self) -> bool:
        """Whether the child is still running."""
        return self._process.poll() is None

    def startup_left_s(self) -> float:
        """How much longer a shutdown may wait for the child to become ready (0 once it is)."""
        if self._ready:
            return 0.0
        return max(0.0, self._started_at + STARTUP_ALLOWANCE_S - time.monotonic())

    def wait_ready(self) -> bool:
        """Wait, within :data:`STARTUP_ALLOWANCE_S` of its start, until the child is ready; whether it is."""
        with self._lock:
            return self._await_ready()

    def export(self, spans: list[SpanRecord], samples: list[MetricSample]) -> None:
        """Buffer one tick's records until the next :meth:`flush`."""
        with self._lock:
            self._spans.extend(spans)
            self._samples.extend(samples)

    def flush(self, *, force: bool = True) -> None:
        """Send what is buffered: now when ``force``, else once :data:`SEND_INTERVAL_S` has passed or
        :data:`SEND_RECORDS` are waiting."""
        if (
            not force
            and time.monotonic() - self._sent_at < SEND_INTERVAL_S
            and len(self._spans) + len(self._samples) < SEND_RECORDS
        ):
            return
        self.send()

    def send(self) -> None:
        """Send everything buffered, as one message."""
        with self._lock:
            spans, samples = self._spans, self._samples
            self._sent_at = time.monotonic()
            if not spans and not samples:
                return
            self._spans, self._samples = [], []
            if not self._send(("data", spans, samples)):
                self._lost(spans, samples)

    def force_flush(self, timeout_s: float = 5.0) -> bool:
        """Send what is buffered and wait until the child's exporters have flushed it."""
        self.send()
        with self._lock:
            if not self._await_ready(timeout_s) or not self._send(("flush",)):
                return False
            return self._read_byte(timeout_s) == _FLUSHED

    def shutdown(self, timeout_s: float = 5.0) -> bool:
        """Send what is buffered, close the pipe and wait for the child to export and exit.

        A child still starting is first waited for to become ready (:meth:`startup_left_s`).

        Returns:
            ``True`` when the child exited cleanly within ``timeout_s`` of being ready; otherwise
            it is killed.
        """
        self.send()
        with self._lock:
            self._alive = False
            stdin = self._process.stdin
            if stdin is not None and not stdin.closed:
                with contextlib.suppress(OSError):  # a dead child has already closed its end
                    stdin.close()
            self._await_ready()
        try:
            return self._process.wait(timeout_s) == 0
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
            _log.warning("telemetry export process did not finish in time; its buffered telemetry is lost")
            return False
        finally:
            if self._process.stdout is not None:
                self._process.stdout.close()

    def _await_ready(self, limit_s: float | None = None) -> bool:
        """Whether the child is ready, waiting for its ready byte within the start-up allowance (and ``limit_s``)."""
        if not self._ready:
            wait_s = self.startup_left_s() if limit_s is None else min(limit_s, self.startup_left_s())
            self._ready = self._read_byte(wait_s) == _READY
        return self._ready

    def _read_byte(self, timeout_s: float) -> bytes:
        """One byte of the child's stdout, or ``b""`` when none came within ``timeout_s`` (or it is gone)."""
        stdout = self._process.stdout
        if stdout is None or stdout.closed:
            return b""
        ready, _, _ = select.select([stdout], [], [], timeout_s)
        return stdout.read(1) if ready else b""

    def _send(self, message: tuple[object, ...]) -> bool:
        stdin = self._process.stdin
        if self._alive and stdin is not None:
            payload = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
            try:
                stdin.write(_HEADER.pack(len(payload)) + payload)
                stdin.flush()
                return True
            except OSError as exc:  # the child is gone: keep the robot running, export here instead
                self._alive = False
                where = "exported by this process" if self._fallback is not None else "dropped"
                _log.warning(f"telemetry export process is gone; tick telemetry is {where} from now on", error=str(exc))
        return False

    def _lost(self, spans: list[SpanRecord], samples: list[MetricSample]) -> None:
        if self._fallback is not None:
            self._fallback.export(spans, samples)
            return
        self.dropped_spans += len(spans)
        self.dropped_samples += len(samples)


def _read_exact(stream: IO[bytes], n: int) -> bytes | None:
    data = stream.read(n)
    return data if data is not None and len(data) == n else None


def serve(
    stdin: IO[bytes],
    stdout: IO[bytes],
    settings: str,
    flush_timeout_s: float = 5.0,
    on_ready: Callable[[], None] | None = None,
) -> int:
    """The child's loop: install the exporters, say it is ready, export what arrives, flush and exit at end of input.

    The final flush is bounded by ``flush_timeout_s``: with the collector unreachable, what is
    still buffered is dropped rather than retried for tens of seconds.
    """
    config = TelemetryConfig(**json.loads(settings))
    config = replace(config, endpoints={k: v for k, v in config.endpoints.items() if k != "logs"})
    providers = install(config)
    pipeline = SdkSpanPipeline.of(trace.get_tracer_provider().get_tracer(TRACER_NAME))
    sink = InProcessSink(pipeline)
    stdout.write(_READY)
    stdout.flush()
    if on_ready is not None:
        on_ready()
    while (header := _read_exact(stdin, _HEADER.size)) is not None:
        payload = _read_exact(stdin, _HEADER.unpack(header)[0])
        if payload is None:
            break
        message = pickle.loads(payload)  # our parent's records, over a private pipe
        if message[0] == "data":
            sink.export(message[1], message[2])
        elif message[0] == "flush":
            for provider in providers:
                provider.force_flush()
            stdout.write(_FLUSHED)
            stdout.flush()

    def flush_and_stop() -> None:
        for provider in providers:
            provider.force_flush(int(flush_timeout_s * 1e3))
            provider.shutdown()

    final = threading.Thread(target=flush_and_stop, name="openral-export-shutdown", daemon=True)
    final.start()
    final.join(flush_timeout_s)
    return 0 if not final.is_alive() else 1


NICENESS: Final = 10
"""How much lower than its parent the export process runs: where cores are short, the tick wins."""


_PR_SET_PDEATHSIG: Final = 1


def _lower_priority() -> None:
    os.nice(NICENESS)


def die_with_parent(parent_pid: int) -> None:
    """Ask the kernel to SIGKILL this process when its parent dies; exit now if it already has."""
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(0)


def main() -> int:
    """Entry point of the child process: ``settings parent_pid flush_timeout_s``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    die_with_parent(int(sys.argv[2]))
    structlog.configure(logger_factory=structlog.PrintLoggerFactory(file=sys.stderr))
    code = serve(sys.stdin.buffer, sys.stdout.buffer, sys.argv[1], float(sys.argv[3]), _lower_priority)
    os._exit(code)  # exporter threads still retrying must not hold the exit


if __name__ == "__main__":
    sys.exit(main())
