"""WorldStateAggregator: freshness from capture stamps, the readers' verdicts, latching telemetry, zero-copy frames."""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from opentelemetry.sdk.metrics.export import InMemoryMetricReader
from opentelemetry.sdk.trace import ReadableSpan
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter

from openral_core import (
    JointState,
    ROSConfigError,
    ROSError,
    ROSPerceptionStale,
    ROSRuntimeError,
    SensorFrame,
    SensorReaderConfig,
    WorldState,
)
from openral_observability import semconv, tracer
from openral_world_state import JOINT_STATE_COMPONENT, WorldStateAggregator

MS = 1_000_000
T0 = 1_000 * MS


@pytest.fixture
def spans(otel: Any) -> Iterator[InMemorySpanExporter]:
    """The session's in-memory span exporter (tests/conftest.py), cleared around the test."""
    otel.exporter.clear()
    yield otel.exporter
    otel.exporter.clear()


@pytest.fixture
def metric_reader(otel: Any) -> InMemoryMetricReader:
    """The session's in-memory metric reader; values are cumulative, so tests compare deltas."""
    reader: InMemoryMetricReader = otel.reader
    return reader


class FakeClock:
    def __init__(self, now_ns: int = T0) -> None:
        self.now_ns = now_ns

    def __call__(self) -> int:
        return self.now_ns

    def advance_ms(self, ms: float) -> None:
        self.now_ns += int(ms * MS)


def _frame(sensor_id: str, stamp_ns: int, data: Any = None, seq: int = 0) -> SensorFrame:
    if data is None:
        data = np.zeros((2, 2, 3), np.uint8)
    return SensorFrame(sensor_id=sensor_id, stamp_ns=stamp_ns, width=2, height=2, data=data, seq=seq)


def _joints(stamp_ns: int, value: float = 0.0) -> JointState:
    return JointState(names=["a", "b"], positions=[value, -value], stamp_ns=stamp_ns)


def _cams(*specs: tuple[str, float, bool]) -> list[SensorReaderConfig]:
    return [SensorReaderConfig(sensor_id=sid, max_age_ms=age, required=req) for sid, age, req in specs]


class Feed:
    """Stands in for the runner's sensor phase: the latest frame per sensor, this tick's failed reads.

    Each :meth:`snapshot` runs inside its own ``world_state.snapshot`` span, as the runner's does.
    """

    def __init__(self, aggregator: WorldStateAggregator) -> None:
        self.aggregator = aggregator
        self.frames: dict[str, SensorFrame] = {}
        self.failures: dict[str, ROSError] = {}

    def read(self, frame: SensorFrame) -> None:
        """The sensor's reader served ``frame``: the latest frame of its sensor from now on."""
        self.frames[frame.sensor_id] = frame

    def read_stale(self, sensor_id: str, age_ms: float | None = None) -> None:
        """This tick's read of ``sensor_id`` found no fresh frame."""
        self.failures[sensor_id] = ROSPerceptionStale(sensor_id, age_ms=age_ms, max_age_ms=None)

    def read_failed(self, sensor_id: str, message: str) -> None:
        """This tick's read of ``sensor_id`` raised."""
        self.failures[sensor_id] = ROSRuntimeError(message)

    def snapshot(self, task: str | None = None) -> WorldState:
        span = tracer().start_span(semconv.SPAN_WORLD_STATE_SNAPSHOT)
        try:
            return self.aggregator.snapshot(self.frames, failures=self.failures, task=task, span=span)
        finally:
            span.end()
            self.failures = {}


def _feed(aggregator: WorldStateAggregator) -> Feed:
    return Feed(aggregator)


def _aggregator(clock: FakeClock, joint_max_age_ms: float = 100.0) -> Feed:
    return Feed(
        WorldStateAggregator(
            joint_max_age_ms=joint_max_age_ms,
            sensors=_cams(("front", 50.0, True), ("wrist", 200.0, False)),
            clock=clock,
        )
    )


def _events(spans: InMemorySpanExporter) -> list[tuple[str, dict[str, Any]]]:
    out: list[tuple[str, dict[str, Any]]] = []
    finished: tuple[ReadableSpan, ...] = spans.get_finished_spans()
    for span in finished:
        if span.name == semconv.SPAN_WORLD_STATE_SNAPSHOT:
            out.extend((event.name, dict(event.attributes or {})) for event in span.events)
    return out


def _updown(reader: InMemoryMetricReader) -> dict[str, int]:
    return _points(reader, semconv.METRIC_WORLD_STATE_COMPONENTS_STALE, "value")


def _hist_counts(reader: InMemoryMetricReader) -> dict[str, int]:
    return _points(reader, semconv.METRIC_WORLD_STATE_STALENESS, "count")


def _points(reader: InMemoryMetricReader, name: str, field: str) -> dict[str, int]:
    data = reader.get_metrics_data()
    out: dict[str, int] = {}
    if data is None:
        return out
    for resource in data.resource_metrics:
        for scope in resource.scope_metrics:
            for metric in scope.metrics:
                if metric.name != name:
                    continue
                for point in metric.data.data_points:
                    component = str((point.attributes or {})[semconv.ATTR_COMPONENT])
                    out[component] = out.get(component, 0) + int(getattr(point, field))
    return out


def _delta(after: dict[str, int], before: dict[str, int]) -> dict[str, int]:
    return {
        k: after.get(k, 0) - before.get(k, 0) for k in set(after) | set(before) if after.get(k, 0) != before.get(k, 0)
    }


# --- diagnostics ---------------------------------------------------------------------------------


def test_every_declared_component_is_diagnosed_before_any_sample() -> None:
    agg = _aggregator(FakeClock())
    ws = agg.snapshot()
    assert list(ws.diagnostics) == [JOINT_STATE_COMPONENT, "front", "wrist"]
    assert agg.aggregator.components == (JOINT_STATE_COMPONENT, "front", "wrist")
    for name, diag in ws.diagnostics.items():
        assert diag.component == name
        assert diag.stale, name
        assert diag.age_ms is None, name
    assert ws.diagnostics["front"].max_age_ms == 50.0
    assert ws.diagnostics["wrist"].max_age_ms == 200.0
    assert ws.diagnostics[JOINT_STATE_COMPONENT].max_age_ms == 100.0
    assert ws.diagnostics["wrist"].required is False
    assert ws.stale_required == [JOINT_STATE_COMPONENT, "front"]
    assert ws.image_frames == {}
    assert ws.joint_state is None


def test_without_sensors_image_frames_is_none() -> None:
    clock = FakeClock()
    agg = _feed(WorldStateAggregator(clock=clock))
    agg.aggregator.update_joint_state(_joints(T0))
    ws = agg.snapshot()
    assert ws.image_frames is None
    assert list(ws.diagnostics) == [JOINT_STATE_COMPONENT]
    assert ws.diagnostics[JOINT_STATE_COMPONENT].healthy


def test_fresh_samples_are_healthy_with_exact_age() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    agg.aggregator.update_joint_state(_joints(T0))
    agg.read(_frame("front", T0 + 10 * MS))
    agg.read(_frame("wrist", T0))
    clock.advance_ms(40)
    ws = agg.snapshot(task="pick the cube")
    assert ws.stamp_ns == clock.now_ns
    assert ws.task == "pick the cube"
    assert ws.diagnostics[JOINT_STATE_COMPONENT].age_ms == pytest.approx(40.0)
    assert ws.diagnostics["front"].age_ms == pytest.approx(30.0)
    assert ws.stale_components == []
    assert all(d.error is None for d in ws.diagnostics.values())


def test_staleness_is_measured_from_capture_stamp_not_arrival() -> None:
    clock = FakeClock(T0 + 1_000 * MS)
    agg = _aggregator(clock)
    # Both arrive right now, but were captured long ago.
    agg.read(_frame("front", clock.now_ns - 60 * MS))
    agg.aggregator.update_joint_state(_joints(clock.now_ns - 150 * MS))
    ws = agg.snapshot()
    assert ws.diagnostics["front"].stale
    assert ws.diagnostics["front"].age_ms == pytest.approx(60.0)
    assert ws.diagnostics[JOINT_STATE_COMPONENT].stale
    assert ws.diagnostics[JOINT_STATE_COMPONENT].age_ms == pytest.approx(150.0)
    assert ws.stale_required == [JOINT_STATE_COMPONENT, "front"]


def test_age_equal_to_limit_is_fresh_and_one_ns_more_is_stale() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    agg.read(_frame("front", T0))
    clock.advance_ms(50)
    assert not agg.snapshot().diagnostics["front"].stale
    clock.now_ns += 1
    assert agg.snapshot().diagnostics["front"].stale


def test_a_stamp_far_in_the_future_is_stale_not_fresh_forever() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    agg.read(_frame("front", T0 + 51 * MS))  # stamped on another clock
    agg.read(_frame("wrist", T0 + 1 * MS))  # within the limit: tolerated
    ws = agg.snapshot()
    assert ws.diagnostics["front"].stale
    assert ws.diagnostics["front"].age_ms == pytest.approx(-51.0)
    assert not ws.diagnostics["wrist"].stale


def test_sample_goes_stale_as_the_clock_advances() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    agg.aggregator.update_joint_state(_joints(T0))
    assert not agg.snapshot().diagnostics[JOINT_STATE_COMPONENT].stale
    clock.advance_ms(100.5)
    assert agg.snapshot().diagnostics[JOINT_STATE_COMPONENT].stale


def test_an_older_joint_state_does_not_replace_a_newer_one() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    new_js = _joints(T0, 1.0)
    agg.aggregator.update_joint_state(new_js)
    agg.aggregator.update_joint_state(_joints(T0 - MS, 2.0))
    assert agg.snapshot().joint_state is new_js
    same_stamp = _joints(T0, 3.0)
    agg.aggregator.update_joint_state(same_stamp)
    assert agg.snapshot().joint_state is same_stamp


# --- frames ---------------------------------------------------------------------------------------


def test_image_frames_are_the_same_objects_over_the_same_pixels() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    pixels = np.arange(2 * 2 * 3, dtype=np.uint8).reshape(2, 2, 3)
    raw = bytearray(range(12))
    front = _frame("front", T0, data=pixels)
    wrist = _frame("wrist", T0, data=raw)
    agg.read(front)
    agg.read(wrist)
    ws = agg.snapshot()
    assert ws.image_frames is not None
    assert ws.image_frames["front"] is front
    assert ws.image_frames["wrist"] is wrist
    assert np.shares_memory(ws.image_frames["front"].as_array(), pixels)
    assert np.shares_memory(ws.image_frames["wrist"].as_array(), np.frombuffer(raw, np.uint8))
    raw[0] = 200  # a write to the capture buffer is visible through the snapshot: no copy was made
    assert ws.image_frames["wrist"].as_array()[0, 0, 0] == 200


def test_image_frames_only_hold_sensors_that_delivered() -> None:
    agg = _aggregator(FakeClock())
    front = _frame("front", T0)
    agg.read(front)
    ws = agg.snapshot()
    assert ws.image_frames == {"front": front}
    assert ws.diagnostics["wrist"].stale


def test_stale_frames_are_still_delivered() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    front = _frame("front", T0)
    agg.read(front)
    clock.advance_ms(500)
    ws = agg.snapshot()
    assert ws.diagnostics["front"].stale
    assert ws.image_frames is not None
    assert ws.image_frames["front"] is front


def test_snapshot_does_not_alias_internal_state() -> None:
    agg = _aggregator(FakeClock())
    agg.read(_frame("front", T0))
    first = agg.snapshot()
    agg.read(_frame("wrist", T0))
    assert first.image_frames is not None
    assert set(first.image_frames) == {"front"}


def test_unknown_sensor_frame_or_failure_is_rejected_naming_the_declared_ones() -> None:
    agg = _aggregator(FakeClock())
    agg.read(_frame("rear", T0))
    with pytest.raises(ROSConfigError, match="unknown sensor 'rear'; declared: front, wrist"):
        agg.snapshot()
    agg.frames.clear()
    agg.read_stale("rear")
    with pytest.raises(ROSConfigError, match="unknown sensor 'rear'"):
        agg.snapshot()


# --- construction ---------------------------------------------------------------------------------


def test_repeated_sensor_id_is_a_config_error() -> None:
    with pytest.raises(ROSConfigError, match=r"sensors\[1\]\.sensor_id") as info:
        WorldStateAggregator(sensors=_cams(("cam", 10.0, True), ("cam", 10.0, True)))
    assert info.value.field == "sensors[1].sensor_id"


def test_sensor_named_like_the_joint_state_is_a_config_error() -> None:
    with pytest.raises(ROSConfigError, match="joint_state"):
        WorldStateAggregator(sensors=_cams((JOINT_STATE_COMPONENT, 10.0, True)))


@pytest.mark.parametrize("age", [0.0, -1.0, float("nan")])
def test_joint_max_age_must_be_positive(age: float) -> None:
    with pytest.raises(ROSConfigError, match="joint_max_age_ms"):
        WorldStateAggregator(joint_max_age_ms=age)


def test_joint_state_can_be_optional() -> None:
    agg = _feed(WorldStateAggregator(joint_required=False, clock=FakeClock()))
    ws = agg.snapshot()
    assert ws.diagnostics[JOINT_STATE_COMPONENT].stale
    assert ws.stale_required == []


# --- errors ---------------------------------------------------------------------------------------


def test_error_makes_a_fresh_component_unhealthy_until_cleared() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    agg.aggregator.update_joint_state(_joints(T0))
    agg.read(_frame("front", T0))
    agg.read(_frame("wrist", T0))
    agg.aggregator.set_error(JOINT_STATE_COMPONENT, "read_state timed out")
    agg.read_failed("wrist", "USB unplugged")
    ws = agg.snapshot()
    diag = ws.diagnostics[JOINT_STATE_COMPONENT]
    assert not diag.stale
    assert diag.error == "read_state timed out"
    assert not diag.healthy
    assert ws.stale_components == [JOINT_STATE_COMPONENT, "wrist"]
    assert ws.stale_required == [JOINT_STATE_COMPONENT]
    agg.aggregator.set_error(JOINT_STATE_COMPONENT, "still timing out")
    agg.read_failed("wrist", "USB unplugged")
    assert agg.snapshot().diagnostics[JOINT_STATE_COMPONENT].error == "still timing out"
    agg.aggregator.clear_error(JOINT_STATE_COMPONENT)
    agg.aggregator.clear_error("front")  # none set: no-op
    agg.read_failed("wrist", "USB unplugged")
    ws = agg.snapshot()
    assert ws.diagnostics[JOINT_STATE_COMPONENT].healthy
    assert ws.stale_components == ["wrist"]
    assert agg.snapshot().stale_components == [], "a sensor's failure is a verdict on one tick's read"


def test_error_on_undeclared_component_is_rejected() -> None:
    agg = _aggregator(FakeClock())
    with pytest.raises(ROSConfigError, match="unknown component 'hal'"):
        agg.aggregator.set_error("hal", "boom")
    with pytest.raises(ROSConfigError, match="unknown component 'hal'"):
        agg.aggregator.clear_error("hal")


# --- telemetry ------------------------------------------------------------------------------------


def test_staleness_latches_once_per_transition(spans: InMemorySpanExporter) -> None:
    clock = FakeClock()
    agg = _feed(WorldStateAggregator(sensors=_cams(("front", 50.0, True)), clock=clock))
    agg.aggregator.update_joint_state(_joints(T0))
    agg.snapshot()
    # The camera has not delivered yet: it latches once, the joint state does not.
    assert _events(spans) == [
        (semconv.EVENT_STALENESS_LATCHED, {semconv.ATTR_COMPONENT: "front"}),
    ]
    agg.snapshot()
    agg.snapshot()
    assert len(_events(spans)) == 1, "a component that stays stale must not emit again"

    spans.clear()
    agg.read(_frame("front", clock.now_ns))
    agg.snapshot()  # recovery: no event
    clock.advance_ms(60)
    agg.aggregator.update_joint_state(_joints(clock.now_ns))
    agg.snapshot()  # front is 60 ms old now
    agg.snapshot()
    assert _events(spans) == [
        (semconv.EVENT_STALENESS_LATCHED, {semconv.ATTR_COMPONENT: "front", semconv.ATTR_SENSOR_AGE_MS: 60.0}),
    ]

    spans.clear()
    agg.read(_frame("front", clock.now_ns))
    agg.snapshot()
    clock.advance_ms(51)
    agg.aggregator.update_joint_state(_joints(clock.now_ns))
    agg.snapshot()
    assert [name for name, _ in _events(spans)] == [semconv.EVENT_STALENESS_LATCHED], "must latch again"


def test_error_latches_once_until_cleared(spans: InMemorySpanExporter) -> None:
    clock = FakeClock()
    agg = _feed(WorldStateAggregator(clock=clock))
    agg.aggregator.update_joint_state(_joints(T0))
    agg.aggregator.set_error(JOINT_STATE_COMPONENT, "bus error")
    agg.snapshot()
    agg.aggregator.set_error(JOINT_STATE_COMPONENT, "bus error again")
    agg.snapshot()
    agg.snapshot()
    assert _events(spans) == [
        (
            semconv.EVENT_ERROR_LATCHED,
            {semconv.ATTR_COMPONENT: JOINT_STATE_COMPONENT, "exception.message": "bus error"},
        ),
    ]
    spans.clear()
    agg.aggregator.clear_error(JOINT_STATE_COMPONENT)
    agg.snapshot()
    assert _events(spans) == []
    agg.aggregator.set_error(JOINT_STATE_COMPONENT, "bus error, third time")
    agg.snapshot()
    assert [name for name, _ in _events(spans)] == [semconv.EVENT_ERROR_LATCHED]


def test_components_stale_counter_goes_up_on_latch_and_down_on_recovery(
    metric_reader: InMemoryMetricReader,
) -> None:
    clock = FakeClock()
    agg = _feed(WorldStateAggregator(sensors=_cams(("latchcam", 50.0, True)), clock=clock))
    before = _updown(metric_reader)
    agg.snapshot()  # both components missing
    agg.snapshot()
    assert _delta(_updown(metric_reader), before) == {JOINT_STATE_COMPONENT: 1, "latchcam": 1}

    agg.aggregator.update_joint_state(_joints(clock.now_ns))
    agg.read(_frame("latchcam", clock.now_ns))
    agg.snapshot()
    assert _delta(_updown(metric_reader), before) == {}

    agg.read_failed("latchcam", "decoder failed")  # fresh but its read failed: unhealthy, counted once
    agg.snapshot()
    assert _delta(_updown(metric_reader), before) == {"latchcam": 1}
    clock.advance_ms(60)  # now also stale: still one unhealthy component
    agg.read_failed("latchcam", "decoder failed")
    agg.snapshot()
    assert _delta(_updown(metric_reader), before) == {"latchcam": 1}
    agg.read(_frame("latchcam", clock.now_ns))
    agg.aggregator.update_joint_state(_joints(clock.now_ns))
    agg.snapshot()
    assert _delta(_updown(metric_reader), before) == {}


# --- threads --------------------------------------------------------------------------------------


@pytest.fixture
def frequent_thread_switches() -> Iterator[None]:
    """Make the GIL change hands every few microseconds so races show up within a short test."""
    previous = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        yield
    finally:
        sys.setswitchinterval(previous)


@pytest.mark.usefixtures("frequent_thread_switches")
def test_concurrent_joint_updates_never_tear_a_snapshot() -> None:
    ticks = 0
    lock = threading.Lock()

    def clock() -> int:
        nonlocal ticks
        with lock:
            ticks += 1
            return T0 + ticks * 1000

    agg = WorldStateAggregator(joint_max_age_ms=1e9, clock=clock)
    n = 2_000
    written: set[int] = set()
    keep: list[JointState] = []  # keeps every written object alive so ids stay unique
    errors: list[BaseException] = []
    start = threading.Barrier(3)

    def joints() -> None:
        try:
            start.wait()
            for k in range(n):
                js = _joints(clock(), float(k))
                written.add(id(js))
                keep.append(js)
                agg.update_joint_state(js)
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=joints) for _ in range(2)]
    for thread in threads:
        thread.start()
    start.wait()
    snapshots = []
    while any(t.is_alive() for t in threads):
        snapshots.append(agg.snapshot())
    for thread in threads:
        thread.join()
    snapshots.append(agg.snapshot())
    assert errors == []
    last_stamp = 0
    for ws in snapshots:
        if ws.joint_state is None:
            continue
        assert id(ws.joint_state) in written
        diagnosis = ws.diagnostics[JOINT_STATE_COMPONENT]
        assert diagnosis.age_ms == (ws.stamp_ns - ws.joint_state.stamp_ns) / 1e6
        assert diagnosis.age_ms >= 0, "snapshot clock read before the joint state it holds"
        assert ws.joint_state.stamp_ns >= last_stamp, "a snapshot went back in time"
        last_stamp = ws.joint_state.stamp_ns


def test_a_readers_stale_verdict_holds_for_one_snapshot_over_a_frame_within_its_age() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    agg.aggregator.update_joint_state(_joints(T0))
    agg.read(_frame("front", T0))
    clock.advance_ms(10)
    agg.read_stale("front", age_ms=75.0)
    marked = agg.snapshot()
    assert marked.diagnostics["front"].stale
    assert marked.diagnostics["front"].age_ms == 75.0
    assert marked.stale_required == ["front"]
    assert marked.image_frames is not None
    assert "front" in marked.image_frames
    after = agg.snapshot()
    assert not after.diagnostics["front"].stale
    assert after.diagnostics["front"].age_ms == pytest.approx(10.0)


def test_a_stale_mark_without_an_age_keeps_the_measured_one() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    agg.read(_frame("wrist", T0))
    clock.advance_ms(20)
    agg.read_stale("wrist")
    diagnosis = agg.snapshot().diagnostics["wrist"]
    assert diagnosis.stale
    assert diagnosis.age_ms == pytest.approx(20.0)


def test_a_failed_read_is_the_sensors_error_for_that_snapshot_only() -> None:
    clock = FakeClock()
    agg = _aggregator(clock)
    agg.read(_frame("wrist", T0))
    agg.read_failed("wrist", "USB unplugged")
    agg.aggregator.set_error(JOINT_STATE_COMPONENT, "bus error")
    failed = agg.snapshot()
    assert failed.diagnostics["wrist"].error == "USB unplugged"
    assert failed.image_frames is not None
    assert "wrist" in failed.image_frames, "the last frame still reaches the skill"
    ws = agg.snapshot()
    assert ws.diagnostics["wrist"].error is None
    assert ws.diagnostics["wrist"].healthy
    assert ws.diagnostics[JOINT_STATE_COMPONENT].error == "bus error"  # set_error holds until cleared
