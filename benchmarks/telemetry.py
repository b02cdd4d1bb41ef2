"""Telemetry benchmark: what tracing and metrics cost per tick.

The same hardware runner (null HAL, hold skill, one camera, world-state aggregator, null safety
client) runs at a fixed rate under three configurations, each in a fresh process because
OpenTelemetry providers can be installed only once per process:

* ``off``: no SDK, the API's no-op tracer and meter (what a deployment without an endpoint gets);
* ``memory``: SDK tracer with an in-memory exporter (``SimpleSpanProcessor``, exported on the
  thread that ends a span: the runner's telemetry worker) and SDK meter with an in-memory reader;
* ``otlp``: ``openral_observability.setup.setup()`` exporting OTLP/HTTP (batch span processor,
  periodic metric reader every second) to a receiver on 127.0.0.1 in this process, which decodes
  every request with ``opentelemetry-proto`` as a collector would. Tick spans and histogram
  samples are exported by ``setup()``'s export process;
* ``otlp_inproc``: the same with ``export_process=False``: the runner's process encodes and posts
  everything itself (what the export process saves);
* ``otlp_10pct``: the same with ``sample_ratio=0.1``: ``setup()``'s tick sampler traces every
  tenth tick whole (as it would under ``openral deploy``'s ``cli.command`` root); the other ticks
  make no phase spans, and metrics still see every tick.

Reported per configuration (median over ``--rounds`` interleaved rounds): the tick's own wall
time (mean, p50, p99, as the runner measures it: the cost on the tick thread), the CPU time of
the runner process's other threads per tick (the telemetry worker and the exporters' background
work), the CPU time of the export process per tick (less what it costs to start and stop one
with nothing to export), and for ``otlp`` the share of spans that
reached the receiver. "added" is each figure minus ``off`` from the same round.

Run:  uv run python benchmarks/telemetry.py [--rate 500] [--seconds 4] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import structlog
from opentelemetry import metrics, trace
from opentelemetry.sdk.metrics import MeterProvider
from opentelemetry.sdk.metrics.export import InMemoryMetricReader
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import BatchSpanProcessor, SimpleSpanProcessor, SpanExporter, SpanExportResult
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter
from opentelemetry.sdk.trace.sampling import ALWAYS_OFF

from _common import machine_line
from openral_core import SensorFrame, SensorReaderConfig
from openral_hal.manifests import load_robot_manifest
from openral_hal.null import NullHAL
from openral_observability.export_process import ExportProcess
from openral_observability.setup import TelemetryConfig, setup
from openral_observability.testing import OTLPReceiver
from openral_rskill.noop import HoldSkill
from openral_runner.hardware import HardwareRunner
from openral_runner.safety import NullSafetyClient
from openral_world_state import WorldStateAggregator

MODES = ("off", "memory", "otlp", "otlp_inproc", "otlp_10pct")
SPANS_PER_TICK = 7  # tick, sensors.read_latest, hal.read_state, world_state.snapshot, inference, safety, send
SAMPLED_RATIO = 0.1
HISTOGRAMS_PER_TICK = 7  # tick, inference, hal read/send, sensor age, world-state staleness x2 (joints, camera)


def _child(mode: str, rate: float, seconds: float, endpoint: str) -> None:
    """Run one configuration and print its figures as JSON."""
    handle = None
    if mode == "memory":
        provider = TracerProvider()
        provider.add_span_processor(SimpleSpanProcessor(InMemorySpanExporter(max_spans=10_000)))
        trace.set_tracer_provider(provider)
        metrics.set_meter_provider(MeterProvider(metric_readers=[InMemoryMetricReader()]))
    elif mode.startswith("otlp"):
        ratio = SAMPLED_RATIO if mode == "otlp_10pct" else None
        handle = setup(
            endpoint=endpoint,
            protocol="http/protobuf",
            sample_ratio=ratio,
            metric_interval_ms=1000,
            export_process=mode != "otlp_inproc",
        )

    structlog.configure(logger_factory=structlog.PrintLoggerFactory(file=sys.stderr))

    class Camera:
        """A reader that always has a fresh 64×48 frame."""

        sensor_id = "front"

        def __init__(self) -> None:
            self._pixels = bytes(64 * 48 * 3)
            self._seq = 0

        def open(self) -> None:
            pass

        def close(self) -> None:
            pass

        def is_open(self) -> bool:
            return True

        def read_synced(self, deadline_ns: int, *, newer_than_ns: int = 0) -> SensorFrame:
            return self.read_latest()

        def read_latest(self, max_age_ms: float | None = None) -> SensorFrame:
            self._seq += 1
            return SensorFrame(
                sensor_id="front", stamp_ns=time.monotonic_ns(), width=64, height=48, seq=self._seq, data=self._pixels
            )

    robot = load_robot_manifest("so101_follower")
    skill = HoldSkill(robot)
    skill.configure()
    skill.activate()
    runner = HardwareRunner(
        thumbnail_hz=0.0,
        hal=NullHAL(robot, {}),
        skill=skill,
        aggregator=WorldStateAggregator(joint_max_age_ms=1000.0, sensors=[SensorReaderConfig(sensor_id="front")]),
        sensor_readers=[Camera()],
        safety_client=NullSafetyClient(),
        rate_hz=rate,
    )
    runner.activate()
    runner.run(int(rate * 0.5))  # warm-up: instruments created, caches filled
    cpu0, thread0 = time.process_time(), time.thread_time()
    result = runner.run(int(rate * seconds))
    # The tick thread busy-waits the last millisecond before each slot, so its CPU time says
    # nothing; the other threads' CPU time is the exporters' background work.
    background_s = (time.process_time() - cpu0) - (time.thread_time() - thread0)
    runner.deactivate()
    flushed = handle.shutdown(timeout_s=30) if handle is not None else True
    exporter_s = _children_cpu_s()  # the export process, once it has exited
    if mode.startswith("otlp") and mode != "otlp_inproc":
        exporter_s -= _idle_export_process_cpu_s(handle.config if handle is not None else None, exporter_s)
    ticks = [t.tick_ms for t in runner.recent_ticks]
    print(
        json.dumps(
            {
                "mode": mode,
                "ticks": result.n_ticks,
                "warmup_ticks": int(rate * 0.5),
                "tick_us_mean": result.tick_ms_mean * 1e3,
                "tick_us_p50": result.tick_ms_p50 * 1e3,
                "tick_us_p99": result.tick_ms_p99 * 1e3,
                "background_cpu_us_per_tick": background_s / result.n_ticks * 1e6,
                "export_process_cpu_us_per_tick": exporter_s / (result.n_ticks + int(rate * 0.5)) * 1e6,
                "achieved_hz": result.effective_rate_hz,
                "missed_slots": result.missed_slots,
                "recent": len(ticks),
                "flushed": flushed,
            }
        )
    )


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _idle_export_process_cpu_s(config: TelemetryConfig | None, before_s: float) -> float:
    """CPU time of an export process that starts (imports, installs exporters) and stops with nothing to do."""
    if config is None:
        return 0.0
    ExportProcess(config).shutdown(timeout_s=30)
    return _children_cpu_s() - before_s


class _NullExporter(SpanExporter):
    def export(self, spans: object) -> SpanExportResult:
        return SpanExportResult.SUCCESS


def _per_operation_us(n: int = 20_000) -> dict[str, float]:
    """SDK cost of one span (recorded, batch-exported to nowhere), one unsampled span, one histogram record."""
    recorded = TracerProvider()
    recorded.add_span_processor(BatchSpanProcessor(_NullExporter()))
    unsampled = TracerProvider(sampler=ALWAYS_OFF)
    meter = MeterProvider(metric_readers=[InMemoryMetricReader()]).get_meter("bench")
    histogram = meter.create_histogram("h", unit="ms")
    attrs = {"openral.sensor.id": "front"}

    def timed(operation: Callable[[], object]) -> float:
        for _ in range(n // 10):
            operation()
        start = time.perf_counter()
        for _ in range(n):
            operation()
        return (time.perf_counter() - start) / n * 1e6

    out: dict[str, float] = {}
    for name, provider in (("recorded span", recorded), ("unsampled span", unsampled)):
        tracer = provider.get_tracer("bench")
        with tracer.start_as_current_span("parent"):
            out[name] = timed(lambda tracer=tracer: tracer.start_span("child", attributes=attrs).end())
        provider.shutdown()
    out["histogram record"] = timed(lambda: histogram.record(1.0, attrs))
    return out


def _run_child(mode: str, args: argparse.Namespace, endpoint: str) -> dict[str, float]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", mode, "--rate", str(args.rate)]
    cmd += ["--seconds", str(args.seconds), "--endpoint", endpoint]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=600)
    if proc.returncode != 0:
        raise SystemExit(f"{mode} run failed:\n{proc.stderr}")
    figures: dict[str, float] = json.loads(proc.stdout.strip().splitlines()[-1])
    return figures


def _percent(shares: list[float]) -> str:
    return f"{statistics.median(shares) * 100:.1f}%" if shares else "not run"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rate", type=float, default=500.0, help="tick rate in Hz")
    parser.add_argument("--seconds", type=float, default=4.0, help="measured run time per configuration")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved rounds; medians are reported")
    parser.add_argument("--modes", default=",".join(MODES), help="comma-separated configurations (off always runs)")
    parser.add_argument("--child", choices=MODES, help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(args.child, args.rate, args.seconds, args.endpoint)
        return

    modes = ["off", *(m for m in MODES if m != "off" and m in args.modes.split(","))]
    unknown = set(args.modes.split(",")) - set(MODES)
    if unknown:
        parser.error(f"unknown configuration(s) {sorted(unknown)}; choose from {', '.join(MODES)}")
    print(machine_line())
    print(f"rate {args.rate:g} Hz, {args.seconds:g} s per configuration, {args.rounds} rounds (medians)")
    runs: dict[str, list[dict[str, float]]] = {mode: [] for mode in modes}
    spans_received: list[float] = []
    sampled: list[float] = []
    with OTLPReceiver() as receiver:
        for _ in range(args.rounds):
            for mode in modes:
                before = len(receiver.spans())
                figures = _run_child(mode, args, receiver.endpoint)
                runs[mode].append(figures)
                expected = (figures["ticks"] + figures["warmup_ticks"]) * SPANS_PER_TICK
                if mode in {"otlp", "otlp_inproc"}:
                    spans_received.append((len(receiver.spans()) - before) / expected)
                elif mode == "otlp_10pct":
                    sampled.append((len(receiver.spans()) - before) / expected)
        requests = dict(receiver.requests)
        received_mb = receiver.bytes_received / 1e6

    def med(mode: str, key: str) -> float:
        return statistics.median(run[key] for run in runs[mode])

    def added(mode: str, key: str) -> float:
        return statistics.median(run[key] - off[key] for run, off in zip(runs[mode], runs["off"], strict=True))

    print(
        f"{'config':<12} {'tick µs mean':>12} {'p50':>8} {'p99':>8} {'bg cpu µs/tick':>14} {'export proc':>11}   "
        f"{'added: tick mean':>16} {'p50':>8}  achieved Hz"
    )
    for mode in modes:
        print(
            f"{mode:<12} {med(mode, 'tick_us_mean'):12.1f} {med(mode, 'tick_us_p50'):8.1f} "
            f"{med(mode, 'tick_us_p99'):8.1f} {med(mode, 'background_cpu_us_per_tick'):14.1f} "
            f"{med(mode, 'export_process_cpu_us_per_tick'):11.1f}   "
            f"{added(mode, 'tick_us_mean'):16.1f} {added(mode, 'tick_us_p50'):8.1f}  {med(mode, 'achieved_hz'):.1f}"
        )
    if spans_received or sampled:
        print(
            f"share of spans that reached the receiver ({SPANS_PER_TICK} per tick): "
            f"otlp, otlp_inproc {_percent(spans_received)}; otlp_10pct {_percent(sampled)}; "
            f"requests {requests}, {received_mb:.1f} MB"
        )
    ops = _per_operation_us()
    print(
        "SDK cost per operation, back to back: "
        + ", ".join(f"{name} {us:.1f} µs" for name, us in ops.items())
        + f"; a tick here makes {SPANS_PER_TICK} spans and {HISTOGRAMS_PER_TICK} histogram records "
        f"(≈ {SPANS_PER_TICK * ops['recorded span'] + HISTOGRAMS_PER_TICK * ops['histogram record']:.0f} µs traced, "
        f"≈ {SPANS_PER_TICK * ops['unsampled span'] + HISTOGRAMS_PER_TICK * ops['histogram record']:.0f} µs unsampled)"
    )
    full = [m for m in ("memory", "otlp") if m in modes]
    if full:
        worst = max(added(m, "tick_us_p50") for m in full)
        worst_mean = max(added(m, "tick_us_mean") for m in full)
        verdict = "within" if worst < 50 else "OVER"
        print(
            f"added per tick on the tick thread with full tracing and metrics (worst of {', '.join(full)}): "
            f"p50 {worst:.1f} µs, {verdict} the 50 µs target; mean {worst_mean:.1f} µs"
        )
    print(machine_line())


if __name__ == "__main__":
    main()
