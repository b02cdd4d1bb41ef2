"""The publisher: the rate limit before a detector runs, the newest frame per camera, one view per frame, sinks."""

from __future__ import annotations

import time

import numpy as np
import pytest

from openral_core import ROSConfigError, SensorFrame
from openral_core.perception import MotionMetadata
from openral_perception.detectors.motion import MotionDetector
from openral_perception.detectors.scene_change import SceneChangeDetector
from openral_perception.frame import DetectorFrame
from openral_perception.publisher import PerceptionEventPublisher, TokenBucket
from openral_perception.testing import RecordingEventSink

H, W = 48, 64


def grey_frame(level: int, stamp_ns: int = 0, sensor_id: str = "cam") -> SensorFrame:
    pixels = np.full((H, W, 3), level, dtype=np.uint8)
    return SensorFrame(sensor_id=sensor_id, stamp_ns=stamp_ns, width=W, height=H, encoding="bgr8", data=pixels)


def test_the_token_bucket_refills_at_its_rate():
    now = [0.0]
    bucket = TokenBucket(2, 4.0, now=lambda: now[0])
    assert [bucket.take() for _ in range(3)] == [True, True, False]
    now[0] = 0.2  # 0.8 of a token
    assert not bucket.take()
    now[0] = 0.25
    assert bucket.take()
    now[0] = 100.0  # never more than its capacity
    assert [bucket.take() for _ in range(3)] == [True, True, False]


class CountingDetector:
    """Fires on every frame it is shown, and keeps the views it was given."""

    def __init__(self, kind: str = "counting") -> None:
        self.kind = kind
        self.seen: list[DetectorFrame] = []
        self.greys: list[np.ndarray] = []

    def detect(self, frame: DetectorFrame) -> MotionMetadata:
        self.seen.append(frame)
        self.greys.append(frame.grey)
        return MotionMetadata(changed_fraction=1.0, box={"x0": 0, "y0": 0, "x1": frame.width, "y1": frame.height})

    def summarise(self, metadata: MotionMetadata) -> str:
        return "counted"


def test_the_rate_limit_comes_before_the_detector_runs():
    now = [0.0]
    detector = CountingDetector()
    sink = RecordingEventSink()
    publisher = PerceptionEventPublisher([detector], [sink], rate_hz=2.0, now=lambda: now[0])
    for _ in range(10):
        publisher.process(grey_frame(10, stamp_ns=1))
    assert len(detector.seen) == 1  # nine frames dropped without running it
    assert publisher.dropped[("cam", "counting")] == 9
    now[0] = 0.5
    publisher.process(grey_frame(10, stamp_ns=2))
    assert len(detector.seen) == 2
    assert [event.stamp_ns for event in sink.events] == [1, 2]
    assert sink.events[0].summary == "counted"
    assert (sink.events[0].width, sink.events[0].height) == (W, H)


def test_every_detector_gets_one_view_whose_grey_and_colour_are_made_once_per_frame(monkeypatch):
    made: list[str] = []
    as_grey, as_bgr = SensorFrame.as_grey, SensorFrame.as_bgr

    def counted_grey(self: SensorFrame) -> np.ndarray:
        made.append("grey")
        return as_grey(self)

    def counted_bgr(self: SensorFrame) -> np.ndarray:
        made.append("bgr")
        return as_bgr(self)

    monkeypatch.setattr(SensorFrame, "as_grey", counted_grey)
    monkeypatch.setattr(SensorFrame, "as_bgr", counted_bgr)
    first, second = CountingDetector("first"), CountingDetector("second")
    publisher = PerceptionEventPublisher([first, second], rate_hz=1000.0, burst=10)
    frame = SensorFrame(
        sensor_id="cam", stamp_ns=1, width=W, height=H, encoding="rgb8", data=np.zeros((H, W, 3), np.uint8)
    )
    publisher.process(frame)
    assert first.seen[0] is second.seen[0]
    assert first.greys[0] is second.greys[0]  # the same array: computed once, not once per detector
    assert made.count("grey") == 1
    assert first.seen[0].bgr is second.seen[0].bgr
    assert made.count("bgr") <= 2  # once for the grey, at most once more for a detector asking for it


def test_the_worker_takes_the_newest_frame_and_close_closes_the_sinks(telemetry):
    from openral_observability import semconv  # noqa: PLC0415

    sink = RecordingEventSink()
    publisher = PerceptionEventPublisher([SceneChangeDetector()], [sink], rate_hz=1000.0, burst=10)
    publisher.submit(grey_frame(0, stamp_ns=1))  # not started: both wait in one slot, the newer wins
    publisher.submit(grey_frame(200, stamp_ns=2))
    assert publisher.dropped[("cam", "superseded")] == 1
    assert publisher.dropped_counts == {("cam", "superseded"): 1}
    publisher.start()
    assert publisher.is_started
    deadline = time.monotonic() + 10
    while publisher.waiting and time.monotonic() < deadline:  # the worker took the 200-grey frame
        time.sleep(0.001)
    publisher.submit(grey_frame(255, stamp_ns=3))
    assert sink.arrived.wait(10)
    publisher.close()
    assert not publisher.is_started
    assert sink.closed
    assert [event.stamp_ns for event in sink.events] == [3]
    spans = telemetry.spans(semconv.SPAN_PERCEPTION_DETECT)
    assert any(event.name == semconv.EVENT_PERCEPTION for span in spans for event in span.events)
    assert telemetry.metric(semconv.METRIC_PERCEPTION_EVENTS, **{semconv.ATTR_PERCEPTION_KIND: "scene_change"}) == 1


class OpeningSink(RecordingEventSink):
    def __init__(self) -> None:
        super().__init__()
        self.opened = 0

    def open(self) -> None:
        self.opened += 1
        self.closed = False


def test_start_opens_the_sinks_and_the_publisher_restarts_after_close():
    sink = OpeningSink()
    publisher = PerceptionEventPublisher([MotionDetector()], [sink], rate_hz=1000.0, burst=10)
    assert sink.opened == 0  # building opens nothing
    publisher.start()
    publisher.start()  # idempotent
    assert sink.opened == 1
    publisher.close()
    publisher.close()
    assert sink.closed
    publisher.start()  # a runner activated again
    assert (sink.opened, sink.closed) == (2, False)
    publisher.submit(grey_frame(0, stamp_ns=1))
    publisher.submit(grey_frame(0, stamp_ns=2, sensor_id="other"))
    publisher.close()  # the frames waiting are still looked at
    assert publisher.handled == 2
    assert sink.closed


def test_what_is_submitted_before_close_is_handled_even_when_never_started():
    detector = CountingDetector()
    publisher = PerceptionEventPublisher([detector], rate_hz=1000.0)
    publisher.submit(grey_frame(5, stamp_ns=1))
    publisher.close()
    assert len(detector.seen) == 1


class FailingDetector:
    kind = "failing"

    def detect(self, frame: DetectorFrame) -> None:
        raise RuntimeError("broken model")

    def summarise(self, metadata: object) -> str:
        return ""


class FailingSink(RecordingEventSink):
    def publish(self, event) -> None:
        raise OSError("link down")


def test_a_failing_detector_or_sink_is_counted_and_the_others_go_on():
    working, sink = CountingDetector(), RecordingEventSink()
    publisher = PerceptionEventPublisher([FailingDetector(), working], [FailingSink(), sink], rate_hz=1000.0)
    events = publisher.process(grey_frame(1, stamp_ns=1))
    assert [event.kind for event in events] == ["counting"]
    assert [event.kind for event in sink.events] == ["counting"]
    assert publisher.errors == 2


def test_a_frame_detectors_cannot_look_at_is_refused():
    publisher = PerceptionEventPublisher([CountingDetector()])
    jpeg = SensorFrame(sensor_id="cam", stamp_ns=1, width=2, height=2, encoding="jpeg", data=b"\xff\xd8")
    with pytest.raises(ValueError, match="jpeg"):
        publisher.process(jpeg)


def test_repeated_kinds_and_bad_settings_are_refused():
    with pytest.raises(ROSConfigError, match="repeat"):
        PerceptionEventPublisher([MotionDetector(), MotionDetector()])
    with pytest.raises(ROSConfigError, match="rate_hz"):
        PerceptionEventPublisher([MotionDetector()], rate_hz=0.0)
