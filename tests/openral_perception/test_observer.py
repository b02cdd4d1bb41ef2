"""The perception observer: built from a deployment's params, fed by reference from the tick, colour order kept."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from openral_core import ObserverContext, ROSConfigError, SensorFrame, TickResult, WorldState
from openral_core.config import validate_model
from openral_observability.observer import TickObserver
from openral_perception.observer import PerceptionObserver
from openral_perception.params import PerceptionParams
from openral_perception.testing import RecordingEventSink

pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")

ROOT = Path(__file__).resolve().parents[2]


ROBOT_ID = "so101_follower"


def _manifest(tmp_path: Path) -> Path:
    (tmp_path / "cube_detector.onnx").write_bytes((ROOT / "models" / "cube_detector.onnx").read_bytes())
    path = tmp_path / "cube.rskill.yaml"
    path.write_text(
        "name: cube\nkind: detector\nlicense: Apache-2.0\ndetector: {model: cube_detector.onnx, labels: [cube]}\n",
        encoding="utf-8",
    )
    return path


def test_a_detector_manifest_runs_on_the_frames_of_each_tick_in_their_colour_order(tmp_path):
    manifest = _manifest(tmp_path)
    observer = PerceptionObserver.from_config(
        {
            "detectors": [{"kind": "motion"}, {"kind": "objects", "params": {"manifest": manifest.name}}],
            "rate_hz": 100,
        },
        ObserverContext(robot_id=ROBOT_ID, rate_hz=30.0, base_dir=tmp_path),
    )
    sink = RecordingEventSink()
    observer.publisher.sinks.append(sink)
    assert isinstance(observer, TickObserver)
    assert not isinstance(observer.publisher, TickObserver)  # one observer; the publisher only takes frames
    assert [d.kind for d in observer.publisher.detectors] == ["motion", "objects"]
    assert not observer.publisher.is_started  # building starts nothing; the runner starts it
    observer.start()
    rgb = np.zeros((120, 160, 3), dtype=np.uint8)
    rgb[...] = (40, 60, 90)  # RGB dark blue
    rgb[40:70, 60:100] = (210, 90, 200)  # RGB magenta: the cube only if the channels are read right
    frame = SensorFrame(sensor_id="front", stamp_ns=5, width=160, height=120, encoding="rgb8", data=rgb)
    world = WorldState(stamp_ns=5, image_frames={"front": frame})
    try:
        observer.on_tick(TickResult(tick_idx=0), world)
        assert sink.arrived.wait(10)
    finally:
        observer.close()
    objects = [e for e in sink.events if e.kind == "objects"]
    assert objects, sink.events
    box = objects[0].metadata.detections[0].box  # type: ignore[union-attr]
    assert box.iou(type(box)(x0=60, y0=40, x1=100, y1=70)) > 0.8


def test_the_earlier_shape_builds_the_same_detectors(tmp_path):
    manifest = _manifest(tmp_path)
    shorthand = PerceptionObserver.from_config(
        {"motion": {"threshold": 20}, "scene_change": {}, "detector_manifest": manifest.name},
        ObserverContext(robot_id=ROBOT_ID, rate_hz=30.0, base_dir=tmp_path),
    )
    listed = PerceptionObserver.from_config(
        {
            "detectors": [
                {"kind": "motion", "params": {"threshold": 20}},
                {"kind": "scene_change"},
                {"kind": "objects", "params": {"manifest": str(manifest)}},
            ]
        },
        ObserverContext(robot_id=ROBOT_ID, rate_hz=30.0),
    )
    for observer in (shorthand, listed):
        assert [d.kind for d in observer.publisher.detectors] == ["motion", "scene_change", "objects"]
        assert observer.publisher.detectors[0].params.threshold == 20  # type: ignore[attr-defined]
        assert observer.publisher.detectors[2].model_id == "cube"  # type: ignore[attr-defined]


def test_only_the_cameras_asked_for_and_frames_with_pixels_are_handed_over():
    observer = PerceptionObserver.from_config(
        {"detectors": [{"kind": "motion"}], "sensors": ["front"]}, ObserverContext(robot_id=ROBOT_ID, rate_hz=30.0)
    )
    pixels = np.zeros((4, 4, 3), dtype=np.uint8)
    frames = {
        "front": SensorFrame(sensor_id="front", stamp_ns=1, width=4, height=4, data=pixels),
        "wrist": SensorFrame(sensor_id="wrist", stamp_ns=1, width=4, height=4, data=pixels),
    }
    observer.on_tick(TickResult(tick_idx=0), WorldState(stamp_ns=1, image_frames=frames))
    assert observer.publisher.waiting == 1
    depth = SensorFrame(sensor_id="front", stamp_ns=2, width=4, height=4, encoding="mono16", data=bytes(32))
    observer.on_tick(TickResult(tick_idx=1), WorldState(stamp_ns=2, image_frames={"front": depth}))
    assert observer.publisher.dropped_counts == {}  # the depth frame was not handed over at all
    observer.close()
    assert observer.publisher.handled == 1


def test_no_detector_is_a_configuration_error_naming_the_kinds():
    with pytest.raises(ROSConfigError, match="no detector") as info:
        PerceptionObserver.from_config({"rate_hz": 5}, ObserverContext(robot_id=ROBOT_ID, rate_hz=30.0))
    assert "motion" in str(info.value)
    assert "objects" in str(info.value)


@pytest.mark.parametrize(
    ("zenoh", "listen"),
    [
        ({}, ["tcp/127.0.0.1:7448"]),
        ({"connect": ["tcp/10.0.0.5:7447"]}, ["tcp/127.0.0.1:0"]),
        ({"listen": ["tcp/0.0.0.0:7448"]}, ["tcp/0.0.0.0:7448"]),
        ({"mode": "client", "connect": ["tcp/10.0.0.5:7447"]}, []),
    ],
)
def test_the_event_session_listens_on_loopback_unless_the_file_says_otherwise(zenoh: dict, listen: list[str]) -> None:
    params = validate_model(PerceptionParams, {"detectors": [{"kind": "motion"}], "zenoh": zenoh})
    assert params.zenoh is not None
    assert params.zenoh.listen == listen


@pytest.mark.parametrize("size", [[0, 0], [-1, 640], [640, 100_000]])
def test_a_model_input_size_out_of_range_is_a_config_error(size: list[int]) -> None:
    with pytest.raises(ROSConfigError, match=r"observers\[\]\.params\.objects\.input_size"):
        PerceptionObserver.from_config(
            {"objects": {"model": "m.onnx", "labels": ["cube"], "input_size": size}},
            ObserverContext(robot_id=ROBOT_ID, rate_hz=30.0),
        )
    with pytest.raises(ROSConfigError, match=r"observers\[\]\.params\.detectors\[0\]\.params\.input_size"):
        PerceptionObserver.from_config(
            {"detectors": [{"kind": "objects", "params": {"model": "m.onnx", "labels": ["c"], "input_size": size}}]},
            ObserverContext(robot_id=ROBOT_ID, rate_hz=30.0),
        )
