"""The GStreamer event leg feeds the event detectors, and the policy's leg keeps its rate."""

from __future__ import annotations

import importlib
import time

import pytest

from openral_core import ROSConfigError, SensorReaderConfig
from openral_runner.backends.gstreamer.perception_tee import MotionDetector, PerceptionEventPublisher

pytestmark = pytest.mark.gstreamer

pytest.importorskip(
    "gi", reason="needs GStreamer and PyGObject: run scripts/install-system-deps.sh, then uv sync --extra gstreamer"
)
try:
    reader_module = importlib.import_module("openral_runner.backends.gstreamer.reader")
except ROSConfigError as exc:  # gi present, GStreamer typelibs missing
    pytest.skip(f"GStreamer introspection data missing: {exc}", allow_module_level=True)

from openral_runner.backends.gstreamer.pipeline import PipelineSpec  # noqa: E402
from openral_runner.testing import RecordingEventSink  # noqa: E402

GStreamerSensorReader = reader_module.GStreamerSensorReader


def test_the_event_leg_feeds_the_detectors_and_the_policy_leg_keeps_its_rate():
    sink = RecordingEventSink()
    publisher = PerceptionEventPublisher([MotionDetector()], [sink], rate_hz=10.0)
    spec = PipelineSpec(
        source="testsrc", pattern="ball", width=160, height=120, fps=30, enable_event_tee=True, event_rate_hz=10
    )
    with GStreamerSensorReader(sensor_id="cam", spec=spec, events=publisher) as reader:
        assert sink.arrived.wait(10), "no motion event from the moving ball"
        deadline = time.monotonic() + 5
        while reader.read_latest(max_age_ms=1000).seq < 10:  # the policy's leg delivers as before
            assert time.monotonic() < deadline
            time.sleep(0.01)
    assert not publisher.is_started  # stopped with the pipeline
    event = sink.events[0]
    assert (event.kind, event.sensor_id, event.width, event.height) == ("motion", "cam", 160, 120)


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
        backend_params={"source": "testsrc", "enable_event_tee": True, "perception": {"motion": {"threshold": 20}}},
    )

    class Robot:
        robot_id = "so101_follower"

    reader = GStreamerSensorReader.from_config(config, hal=None, robot=Robot(), base_dir=tmp_path)
    assert reader.events is not None
    assert [d.kind for d in reader.events.detectors] == ["motion"]
    wrong = config.model_copy(
        update={"backend_params": {"source": "testsrc", "enable_event_tee": True, "perception": {"motoin": {}}}}
    )
    with pytest.raises(ROSConfigError, match=r"backend_params\.perception"):
        GStreamerSensorReader.from_config(wrong, hal=None, robot=Robot(), base_dir=tmp_path)
    off = config.model_copy(update={"backend_params": {"source": "testsrc", "perception": {"motion": {}}}})
    with pytest.raises(ROSConfigError, match="enable_event_tee"):
        GStreamerSensorReader.from_config(off, hal=None, robot=Robot(), base_dir=tmp_path)
