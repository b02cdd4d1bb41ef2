"""The specification's module paths still name perception's parts, as plain re-exports."""

from __future__ import annotations

import importlib

import pytest

LIGHT_PATHS = [
    ("openral_runner.perception", "openral_perception.observer", ["PerceptionObserver", "build_publisher"]),
    ("openral_runner.perception_params", "openral_perception.params", ["PerceptionParams", "DEFAULT_EVENT_LISTEN"]),
    (
        "openral_runner.backends.gstreamer.perception_tee",
        "openral_perception.publisher",
        ["PerceptionEventPublisher", "TokenBucket", "TOPIC_PREFIX", "EventSink"],
    ),
    ("openral_runner.backends.gstreamer.perception_tee", "openral_perception.detectors.motion", ["MotionDetector"]),
    ("openral_runner.backends.gstreamer.detector_factory", "openral_perception.detectors.factory", ["model_path"]),
    ("openral_runner.backends.reward", "openral_perception.reward", ["Frame", "RollingFrameBuffer", "trend"]),
    ("openral_runner.backends.reward.frames", "openral_perception.reward.frames", ["RollingFrameBuffer"]),
    ("openral_runner.world_cloud_bridge", "openral_perception.world_cloud", ["encode_world_cloud_png"]),
]


@pytest.mark.parametrize(("spec_path", "home", "names"), LIGHT_PATHS)
def test_the_specification_paths_name_the_same_objects(spec_path: str, home: str, names: list[str]) -> None:
    spec_module, home_module = importlib.import_module(spec_path), importlib.import_module(home)
    for name in names:
        assert getattr(spec_module, name) is getattr(home_module, name), name
        assert name in spec_module.__all__


def test_the_heavy_specification_paths_name_the_same_objects():
    pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")
    pytest.importorskip("zenoh", reason="needs the 'remote' extra")
    objects = importlib.import_module("openral_runner.backends.gstreamer.objects_detector")
    client = importlib.import_module("openral_runner.backends.reward.client")
    from openral_perception.detectors.objects import ObjectsDetector  # noqa: PLC0415
    from openral_perception.reward.client import RewardMonitor  # noqa: PLC0415

    assert objects.ObjectsDetector is ObjectsDetector
    assert client.RewardMonitor is RewardMonitor
