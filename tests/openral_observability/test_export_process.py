"""The export process: tick records sent over its pipe reach a collector as the SDK would export them."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from openral_observability import semconv
from openral_observability.deferred import MetricSample
from openral_observability.export_process import ExportProcess
from openral_observability.setup import TelemetryConfig, resolve_config
from openral_observability.span_pipeline import SpanRecord
from openral_observability.testing import OTLPReceiver

TRACE_ID = 0x0AF7651916CD43DD8448EB211C80319C
TICK_ID = 0x00F067AA0BA902B7
PARENT_ID = 0xB7AD6B7169203331


def _records() -> list[SpanRecord]:
    tick = SpanRecord(
        name=semconv.SPAN_TICK,
        trace_id=TRACE_ID,
        span_id=TICK_ID,
        trace_flags=1,
        trace_state=None,
        parent_span_id=PARENT_ID,
        parent_is_remote=False,
        start_ns=1_000_000_000,
        end_ns=1_000_500_000,
        attributes={semconv.ATTR_TICK_IDX: 3, semconv.ATTR_ACTION_APPLIED: True},
        events=[(semconv.EVENT_DEADLINE_MISSED, {semconv.ATTR_LATENESS_MS: 0.25}, 1_000_400_000)],
        status_code=2,
        status_description="deadline missed",
    )
    phase = tick._replace(
        name=semconv.SPAN_HAL_SEND_ACTION,
        span_id=TICK_ID + 1,
        parent_span_id=TICK_ID,
        start_ns=1_000_300_000,
        end_ns=1_000_350_000,
        attributes=None,
        events=[],
        status_code=0,
        status_description=None,
    )
    return [tick, phase]


@pytest.fixture
def receiver() -> Iterator[OTLPReceiver]:
    with OTLPReceiver() as running:
        yield running


@pytest.fixture
def config(receiver: OTLPReceiver, monkeypatch: pytest.MonkeyPatch) -> TelemetryConfig:
    for key in list(os.environ):
        if key.startswith("OTEL_"):
            monkeypatch.delenv(key)
    resolved = resolve_config(endpoint=receiver.endpoint, service_name="arm-3", metric_interval_ms=60_000)
    assert resolved is not None
    return resolved


def test_records_are_exported_with_their_ids_times_events_and_samples(
    receiver: OTLPReceiver, config: TelemetryConfig
) -> None:
    process = ExportProcess(config)
    process.export(_records(), [(semconv.METRIC_TICK_DURATION, 0.5, {semconv.ATTR_SKILL_ID: "probe"})])
    process.export([], [(semconv.METRIC_TICK_DURATION, 1.5, {semconv.ATTR_SKILL_ID: "probe"})])
    assert process.shutdown(timeout_s=20)
    spans = {s.name: s for s in receiver.spans()}
    tick, send = spans[semconv.SPAN_TICK], spans[semconv.SPAN_HAL_SEND_ACTION]
    assert int.from_bytes(tick.trace_id) == TRACE_ID
    assert int.from_bytes(tick.span_id) == TICK_ID
    assert int.from_bytes(tick.parent_span_id) == PARENT_ID
    assert send.parent_span_id == tick.span_id
    assert (tick.start_time_unix_nano, tick.end_time_unix_nano) == (1_000_000_000, 1_000_500_000)
    assert {kv.key: kv.value.int_value for kv in tick.attributes}[semconv.ATTR_TICK_IDX] == 3
    (event,) = tick.events
    assert event.name == semconv.EVENT_DEADLINE_MISSED
    assert event.time_unix_nano == 1_000_400_000
    assert tick.status.code == 2
    assert tick.status.message == "deadline missed"
    assert receiver.resource_attributes()["service.name"] == "arm-3"
    metric = [m for m in receiver.metrics() if m.name == semconv.METRIC_TICK_DURATION][-1]  # cumulative
    point = metric.histogram.data_points[-1]
    assert (point.count, point.sum) == (2, 2.0)
    assert 0.01 in point.explicit_bounds  # the millisecond buckets setup() installs


def test_force_flush_delivers_while_the_process_runs(receiver: OTLPReceiver, config: TelemetryConfig) -> None:
    process = ExportProcess(config)
    try:
        process.export(_records(), [])
        assert process.force_flush(timeout_s=20)
        assert len(receiver.spans()) == 2
    finally:
        assert process.shutdown(timeout_s=20)


def test_a_child_slow_to_start_is_waited_for_and_loses_nothing(
    receiver: OTLPReceiver, config: TelemetryConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a machine short of cores the child's imports can outlast a short run: shutdown waits for them."""
    (tmp_path / "sitecustomize.py").write_text("import time\ntime.sleep(3.0)\n")  # runs first in the child
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")])))
    process = ExportProcess(config)
    process.export(_records(), [(semconv.METRIC_TICK_DURATION, 0.5, {semconv.ATTR_SKILL_ID: "probe"})])
    assert process.startup_left_s() > 0  # still starting
    assert process.shutdown(timeout_s=1.0)  # the second is counted from when it is ready
    assert len(receiver.spans()) == 2
    assert any(m.name == semconv.METRIC_TICK_DURATION for m in receiver.metrics())


def test_an_interrupt_to_the_process_group_does_not_lose_the_buffer(
    receiver: OTLPReceiver, config: TelemetryConfig
) -> None:
    process = ExportProcess(config)
    process.export(_records(), [])
    process.flush()
    assert process.force_flush(timeout_s=20)  # the child is up and has installed its handlers
    os.kill(process.pid, signal.SIGINT)  # what a Ctrl-C in the terminal also sends the child
    os.kill(process.pid, signal.SIGTERM)
    process.export(_records()[:1], [])
    assert process.shutdown(timeout_s=20)
    assert len(receiver.spans()) == 3


class RecordingSink:
    """A fallback that keeps what it is given."""

    def __init__(self) -> None:
        self.spans: list[SpanRecord] = []
        self.samples: list[MetricSample] = []

    def export(self, spans: list[SpanRecord], samples: list[MetricSample]) -> None:
        self.spans += spans
        self.samples += samples

    def flush(self, *, force: bool) -> None:
        pass


def _killed(process: ExportProcess) -> ExportProcess:
    os.kill(process.pid, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while process.running and time.monotonic() < deadline:
        time.sleep(0.01)
    return process


def test_records_go_to_the_fallback_once_the_export_process_is_gone(config: TelemetryConfig) -> None:
    fallback = RecordingSink()
    process = _killed(ExportProcess(config, fallback=fallback))
    for _ in range(3):
        process.export(_records(), [(semconv.METRIC_TICK_DURATION, 1.0, None)])
        process.flush()
    assert fallback.spans == _records() * 3  # nothing lost: this process exports them instead
    assert len(fallback.samples) == 3
    assert (process.dropped_spans, process.dropped_samples) == (0, 0)
    assert not process.shutdown(timeout_s=5)


def test_without_a_fallback_a_dead_export_process_counts_what_it_drops(config: TelemetryConfig) -> None:
    process = _killed(ExportProcess(config))
    for _ in range(3):
        process.export(_records(), [(semconv.METRIC_TICK_DURATION, 1.0, None)])
        process.flush()
    assert (process.dropped_spans, process.dropped_samples) == (6, 3)
    assert not process.force_flush(timeout_s=1)
    assert not process.shutdown(timeout_s=5)


PARENT = """
import sys
from openral_observability.export_process import ExportProcess
from openral_observability.setup import resolve_config
from openral_observability.span_pipeline import SpanRecord
config = resolve_config(endpoint=sys.argv[1], service_name="arm", metric_interval_ms=60_000)
process = ExportProcess(config)
span = SpanRecord("rskill.tick", 1, 2, 1, None, None, False, 1, 2, None, [], 0, None)
process.export([span] * 500, [])  # buffered telemetry the child would try to deliver
process.send()
print(process.pid, flush=True)
sys.stdin.read()  # until the test kills this process
"""


def _unreachable_endpoint() -> str:
    import socket  # noqa: PLC0415

    with socket.socket() as probe:  # a port nothing listens on: connections are refused
        probe.bind(("127.0.0.1", 0))
        return f"http://127.0.0.1:{probe.getsockname()[1]}"


def _gone(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        with open(f"/proc/{pid}/stat") as stat:  # a zombie is gone too: it runs nothing
            if stat.read().split(")")[-1].split()[0] == "Z":
                return True
        time.sleep(0.01)
    return False


def test_the_export_process_dies_with_a_sigkilled_parent(monkeypatch: pytest.MonkeyPatch) -> None:
    import subprocess  # noqa: PLC0415
    import sys  # noqa: PLC0415

    for key in list(os.environ):
        if key.startswith("OTEL_"):
            monkeypatch.delenv(key)
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, _unreachable_endpoint()],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        assert not _gone(child, 0.2), "the export process runs while its parent does"
        parent.kill()
        parent.wait(10)
        # The kernel kills it at once; a loaded machine may take seconds to schedule its exit (nice +10).
        assert _gone(child, 30.0), "the export process outlived its SIGKILLed parent"
    finally:
        if parent.poll() is None:
            parent.kill()
        for stream in (parent.stdin, parent.stdout):
            if stream is not None:
                stream.close()


def test_shutdown_with_the_collector_unreachable_is_bounded_by_the_flush_timeout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for key in list(os.environ):
        if key.startswith("OTEL_"):
            monkeypatch.delenv(key)
    config = resolve_config(endpoint=_unreachable_endpoint(), service_name="arm", metric_interval_ms=60_000)
    assert config is not None
    process = ExportProcess(config, flush_timeout_s=1.0)
    process.export(_records() * 50, [])
    started = time.monotonic()
    # The parent would wait 30 s before killing a child whose flush kept retrying; a child that bounds
    # its own flush exits after about 1 s, well within 10 s even on a loaded machine.
    process.shutdown(timeout_s=30)
    assert time.monotonic() - started < 10.0, "the child's own flush is bounded, not the exporter's retries"
    assert not process.running
