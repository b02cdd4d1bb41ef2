"""Event detectors over random frames, the token bucket, and the publisher's worker."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openral_core import ROSConfigError
from openral_core.perception import MotionMetadata, SceneChangeMetadata
from openral_runner.backends.gstreamer.perception_tee import (
    MotionDetector,
    PerceptionEventPublisher,
    SceneChangeDetector,
    TokenBucket,
    frame_pixels,
    grey_levels,
)
from openral_runner.testing import RecordingEventSink

H, W = 48, 64


def grey_frame(level: int) -> np.ndarray:
    return np.full((H, W, 3), level, dtype=np.uint8)


frames = st.one_of(
    st.integers(0, 255).map(grey_frame),
    st.integers(0, 2**32 - 1).map(lambda seed: np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)),
)


@settings(max_examples=60, deadline=None)
@given(first=frames, second=frames)
def test_detectors_take_any_frame_and_stay_in_their_ranges(first, second):
    motion, scene = MotionDetector(), SceneChangeDetector()
    for detector in (motion, scene):
        assert detector.detect(first, W, H, "cam") is None  # nothing to compare with yet
    found = motion.detect(second, W, H, "cam")
    if found is not None:
        assert 0 < found.changed_fraction <= 1
        assert 0 <= found.box.x0 < found.box.x1 <= W
        assert 0 <= found.box.y0 < found.box.y1 <= H
    change = scene.detect(second, W, H, "cam")
    if change is not None:
        assert 0.5 < change.distance <= 2.0 + 1e-9
    same = SceneChangeDetector()
    same.detect(second, W, H, "cam")
    assert same.detect(second.copy(), W, H, "cam") is None  # the same frame again: no change
    still = MotionDetector()
    still.detect(second, W, H, "cam")
    assert still.detect(second.copy(), W, H, "cam") is None


def _padded_rows(frame: np.ndarray) -> bytes:
    """``frame`` as GStreamer lays BGR out: each row padded to a multiple of 4 bytes."""
    height, width = frame.shape[:2]
    stride = -(-width * 3 // 4) * 4
    rows = np.zeros((height, stride), dtype=np.uint8)
    rows[:, : width * 3] = frame.reshape(height, width * 3)
    return rows.tobytes()


def _buffers(frame: np.ndarray) -> dict[str, object]:
    """One frame in every form a caller may hand a detector."""
    flat = frame.tobytes()
    return {
        "bytes": flat,
        "bytearray": bytearray(flat),
        "memoryview": memoryview(flat),
        "flat array": frame.reshape(-1),
        "shaped array": frame,
        "padded rows": _padded_rows(frame),
    }


@pytest.mark.parametrize("detector_type", [MotionDetector, SceneChangeDetector])
@pytest.mark.parametrize("width", [W, 7])  # 7 * 3 bytes: rows that GStreamer pads
def test_detectors_take_frames_as_the_specification_passes_them(detector_type, width):
    first = np.random.default_rng(width).integers(40, 48, (H, width, 3), dtype=np.uint8)  # a dim, textured view
    second = first.copy()
    second[: H // 2] += 180  # its top half lights up: both detectors fire
    expected = detector_type()
    expected.detect(first, width, H, "cam0")
    wanted = expected.detect(second, width, H, "cam0")
    assert wanted is not None
    befores, afters = _buffers(first), _buffers(second)
    for form in befores:
        before, after = befores[form], afters[form]
        detector = detector_type()
        assert detector.detect(before, width, H, "cam0") is None, form
        assert detector.detect(after, width, H, "cam0") == wanted, form


@pytest.mark.parametrize("form", ["bytes", "bytearray", "memoryview", "flat array", "shaped array"])
def test_frame_pixels_views_the_callers_buffer_without_a_copy(form):
    frame = np.random.default_rng(1).integers(0, 256, (H, W, 3), dtype=np.uint8)
    buffer = _buffers(frame)[form]
    pixels = frame_pixels(buffer, W, H)  # type: ignore[arg-type]
    assert pixels.shape == (H, W, 3)
    np.testing.assert_array_equal(pixels, frame)
    assert np.shares_memory(pixels, np.asarray(memoryview(buffer)))  # type: ignore[arg-type]


def test_padded_rows_are_viewed_with_the_padding_cut_off():
    frame = np.random.default_rng(2).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    buffer = _padded_rows(frame)
    pixels = frame_pixels(buffer, 7, 5)
    np.testing.assert_array_equal(pixels, frame)
    assert np.shares_memory(pixels, np.frombuffer(buffer, np.uint8))


@pytest.mark.parametrize(
    ("frame", "match"),
    [
        (bytes(W * H * 3 - 1), f"a {W}x{H} BGR frame is {W * H * 3} bytes"),
        (bytes(W * H), f"a {W}x{H} BGR frame is {W * H * 3} bytes"),
        (np.zeros((W, H, 3), dtype=np.uint8), f"expected a {W}x{H} frame"),
        (np.zeros((H, W, 3), dtype=np.float32), "uint8"),
    ],
)
def test_a_frame_of_the_wrong_size_is_a_clear_error(frame, match):
    for detector in (MotionDetector(), SceneChangeDetector()):
        with pytest.raises(ValueError, match=match):
            detector.detect(frame, W, H, "cam0")


def test_grey_levels_cover_the_whole_range_without_wrapping():
    assert grey_levels(grey_frame(255)).min() == 255
    assert grey_levels(grey_frame(0)).max() == 0
    assert grey_levels(grey_frame(200)).mean() == pytest.approx(200, abs=1)
    histogram = SceneChangeDetector().histogram(grey_levels(grey_frame(255)))
    assert histogram[-1] == pytest.approx(1.0)  # an all-white frame is all in the top bin


@pytest.mark.parametrize(("before", "after"), [(200, 240), (0, 255), (255, 0), (128, 200)])
def test_a_bright_scene_changing_fires(before, after):
    detector = SceneChangeDetector()
    detector.detect(grey_frame(before), W, H, "cam")
    found = detector.detect(grey_frame(after), W, H, "cam")
    assert isinstance(found, SceneChangeMetadata)
    assert found.distance == pytest.approx(2.0)
    assert found.mean_grey_after == pytest.approx(after, abs=1)


def test_one_changed_pixel_neither_fires_nor_widens_the_box():
    detector = MotionDetector()
    base = grey_frame(100)
    detector.detect(base, W, H, "cam")
    speck = base.copy()
    speck[H - 1, W - 1] = 255
    assert detector.detect(speck, W, H, "cam") is None
    moved = speck.copy()
    moved[8:24, 16:32] = 250  # a real object: two cells by two
    found = detector.detect(moved, W, H, "cam")
    assert isinstance(found, MotionMetadata)
    assert (found.box.x0, found.box.y0, found.box.x1, found.box.y1) == (16, 8, 32, 24)
    another = moved.copy()
    another[0, 0] = 0  # and a far noisy pixel at the same time
    another[8:24, 16:32] = 10
    found = detector.detect(another, W, H, "cam")
    assert found is not None
    assert (found.box.x0, found.box.y0, found.box.x1, found.box.y1) == (16, 8, 32, 24)


def test_each_sensor_is_compared_with_its_own_previous_frame():
    detector = MotionDetector()
    detector.detect(grey_frame(0), W, H, "left")
    detector.detect(grey_frame(255), W, H, "right")
    assert detector.detect(grey_frame(0), W, H, "left") is None
    assert detector.detect(grey_frame(0), W, H, "right") is not None


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
    kind = "counting"

    def __init__(self) -> None:
        self.calls = 0

    def detect(self, frame_bgr, width, height, sensor_id):
        self.calls += 1
        return MotionMetadata(changed_fraction=1.0, box={"x0": 0, "y0": 0, "x1": width, "y1": height})

    def summarise(self, metadata) -> str:
        return "counted"


def test_the_rate_limit_comes_before_the_detector_runs():
    now = [0.0]
    detector = CountingDetector()
    sink = RecordingEventSink()
    publisher = PerceptionEventPublisher([detector], [sink], rate_hz=2.0, now=lambda: now[0])
    frame = grey_frame(10)
    for _ in range(10):
        publisher.process(frame, "cam", 1)
    assert detector.calls == 1  # nine frames dropped without running it
    assert publisher.dropped[("cam", "counting")] == 9
    now[0] = 0.5
    publisher.process(frame, "cam", 2)
    assert detector.calls == 2
    assert [event.stamp_ns for event in sink.events] == [1, 2]
    assert sink.events[0].summary == "counted"
    assert sink.events[0].width == W


def test_the_worker_takes_the_newest_frame_and_stop_closes_the_sinks(telemetry):
    from openral_observability import semconv  # noqa: PLC0415

    sink = RecordingEventSink()
    publisher = PerceptionEventPublisher([SceneChangeDetector()], [sink], rate_hz=1000.0, burst=10)
    publisher.submit(grey_frame(0), "cam", 1)  # not started: both wait in one slot, the newer wins
    publisher.submit(grey_frame(200), "cam", 2)
    assert publisher.dropped[("cam", "superseded")] == 1
    publisher.start()
    deadline = time.monotonic() + 10
    while publisher.waiting and time.monotonic() < deadline:  # the worker took the 200-grey frame
        time.sleep(0.001)
    publisher.submit(grey_frame(255), "cam", 3)
    assert sink.arrived.wait(10)
    publisher.stop()
    assert sink.closed
    assert [event.stamp_ns for event in sink.events] == [3]
    spans = telemetry.spans(semconv.SPAN_PERCEPTION_DETECT)
    assert any(event.name == semconv.EVENT_PERCEPTION for span in spans for event in span.events)
    assert telemetry.metric(semconv.METRIC_PERCEPTION_EVENTS, **{semconv.ATTR_PERCEPTION_KIND: "scene_change"}) == 1


def test_repeated_kinds_and_bad_settings_are_refused():
    with pytest.raises(ROSConfigError, match="repeat"):
        PerceptionEventPublisher([MotionDetector(), MotionDetector()])
    with pytest.raises(ROSConfigError, match="threshold"):
        SceneChangeDetector(threshold=3.0)
