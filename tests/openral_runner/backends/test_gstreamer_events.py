"""The GStreamer event leg feeds a frame consumer (the event detectors), and the policy's leg keeps its rate."""

from __future__ import annotations

import importlib
import threading
import time

import numpy as np
import pytest

from openral_core import ROSConfigError, SensorFrame, SensorReaderConfig
from openral_perception.detectors.motion import MotionDetector
from openral_perception.publisher import PerceptionEventPublisher
from openral_perception.testing import RecordingEventSink

pytestmark = pytest.mark.gstreamer

pytest.importorskip(
    "gi", reason="needs GStreamer and PyGObject: run scripts/install-system-deps.sh, then uv sync --extra gstreamer"
)
try:
    reader_module = importlib.import_module("openral_runner.backends.gstreamer.reader")
except ROSConfigError as exc:  # gi present, GStreamer typelibs missing
    pytest.skip(f"GStreamer introspection data missing: {exc}", allow_module_level=True)

from openral_runner.backends.gstreamer.pipeline import PipelineSpec  # noqa: E402

GStreamerSensorReader = reader_module.GStreamerSensorReader


def test_the_event_leg_feeds_the_detectors_and_the_policy_leg_keeps_its_rate():
    sink = RecordingEventSink()
    publisher = PerceptionEventPublisher([MotionDetector()], [sink], rate_hz=10.0)
    spec = PipelineSpec(
        source="testsrc", pattern="ball", width=160, height=120, fps=30, enable_event_tee=True, event_rate_hz=10
    )
    with GStreamerSensorReader(sensor_id="cam", spec=spec, events=publisher) as reader:
        assert publisher.is_started
        assert sink.arrived.wait(10), "no motion event from the moving ball"
        deadline = time.monotonic() + 5
        while reader.read_latest(max_age_ms=1000).seq < 10:  # the policy's leg delivers as before
            assert time.monotonic() < deadline
            time.sleep(0.01)
    assert not publisher.is_started  # closed with the pipeline
    event = sink.events[0]
    assert (event.kind, event.sensor_id, event.width, event.height) == ("motion", "cam", 160, 120)


class Frames:
    """A frame consumer that keeps what the event leg hands it."""

    def __init__(self) -> None:
        self.frames: list[SensorFrame] = []
        self.arrived = threading.Event()
        self.started = self.closed = 0

    def start(self) -> None:
        self.started += 1

    def submit(self, frame: SensorFrame) -> None:
        self.frames.append(frame)
        self.arrived.set()

    def close(self) -> None:
        self.closed += 1


def test_the_event_legs_frames_have_padded_rows_cut_and_are_stamped_at_capture():
    consumer = Frames()
    spec = PipelineSpec(  # 161 BGR pixels = 483 bytes a row, padded to 484
        source="testsrc", pattern="solid-color", width=161, height=30, fps=30, enable_event_tee=True, event_rate_hz=10
    )
    with GStreamerSensorReader(sensor_id="cam", spec=spec, events=consumer) as reader:
        assert consumer.arrived.wait(10), "no frame on the event leg"
        policy = reader.read_synced(time.monotonic_ns() + 5_000_000_000)
    assert (consumer.started, consumer.closed) == (1, 1)
    frame = consumer.frames[0]
    assert (frame.sensor_id, frame.width, frame.height, frame.encoding) == ("cam", 161, 30, "bgr8")
    pixels = frame.as_array()
    assert pixels.shape == (30, 161, 3)
    assert (pixels == pixels[0, 0]).all(), "rows drift: the row stride was ignored"
    np.testing.assert_array_equal(pixels[0, 0], policy.as_bgr()[0, 0])
    assert 0 < frame.stamp_ns <= time.monotonic_ns()


def test_event_detectors_need_the_event_leg():
    publisher = PerceptionEventPublisher([MotionDetector()])
    with pytest.raises(ROSConfigError, match="enable_event_tee"):
        GStreamerSensorReader(sensor_id="cam", spec=PipelineSpec(source="testsrc"), events=publisher)


def test_a_deployment_sets_perception_on_a_camera_and_a_wrong_key_is_named(tmp_path):
    config = SensorReaderConfig(
        sensor_id="cam",
        backend="gstreamer",
        width=160,
        height=120,
        fps=30,
        backend_params={
            "source": "testsrc",
            "enable_event_tee": True,
            "perception": {"detectors": [{"kind": "motion", "params": {"threshold": 20}}]},
        },
    )

    class Robot:
        robot_id = "so101_follower"

    reader = GStreamerSensorReader.from_config(config, hal=None, robot=Robot(), base_dir=tmp_path)
    assert reader.events is not None
    assert [d.kind for d in reader.events.detectors] == ["motion"]

    def with_perception(perception: dict, **params: object) -> SensorReaderConfig:
        backend_params = {"source": "testsrc", "enable_event_tee": True, "perception": perception, **params}
        return config.model_copy(update={"backend_params": backend_params})

    with pytest.raises(ROSConfigError, match=r"backend_params\.perception"):
        GStreamerSensorReader.from_config(with_perception({"motoin": {}}), hal=None, robot=Robot(), base_dir=tmp_path)
    wrong_param = with_perception({"detectors": [{"kind": "motion", "params": {"treshold": 20}}]})
    with pytest.raises(ROSConfigError, match=r"sensors\[cam\]\.backend_params\.perception\.detectors\[0\]\.params"):
        GStreamerSensorReader.from_config(wrong_param, hal=None, robot=Robot(), base_dir=tmp_path)
    off = with_perception({"motion": {}}, enable_event_tee=False)
    with pytest.raises(ROSConfigError, match="enable_event_tee"):
        GStreamerSensorReader.from_config(off, hal=None, robot=Robot(), base_dir=tmp_path)
