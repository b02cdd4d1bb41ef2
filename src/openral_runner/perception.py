"""``perception`` observer: event detectors on the camera frames the runner already has.

The tick only hands each selected camera's frame (a view, no copy) to a
:class:`~openral_runner.backends.gstreamer.perception_tee.PerceptionEventPublisher`; its worker
runs motion, scene-change and object detectors, rate-limited per camera and kind, and publishes
the events on Zenoh (``openral/<robot>/perception/<kind>``, with ``zenoh:`` set) and in telemetry.

.. code-block:: yaml

    observers:
      - id: perception
        params:
          rate_hz: 5
          motion: {threshold: 25}
          scene_change: {threshold: 0.5}
          objects: {model: models/cube_detector.onnx, labels: [cube]}
          zenoh: {listen: [tcp/127.0.0.1:7448]}
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from openral_core import FrameEncoding, ROSConfigError, TickResult, WorldState
from openral_core.config import validate_model
from openral_core.config_files import is_regular_file, require_user_file, resolve_user_path
from openral_observability.observer import TickObserver
from openral_rskill.manifest import RSkillManifest
from openral_runner.backends.gstreamer.perception_tee import (
    EventDetector,
    EventSink,
    MotionDetector,
    PerceptionEventPublisher,
    SceneChangeDetector,
)
from openral_runner.perception_params import PerceptionParams


def bgr_view(frame_array: np.ndarray, encoding: FrameEncoding) -> np.ndarray | None:
    """A BGR (or grey) view of a frame's pixels without copying; ``None`` for compressed or 16-bit frames."""
    if encoding in (FrameEncoding.BGR8, FrameEncoding.MONO8):
        return frame_array
    if encoding == FrameEncoding.RGB8:
        return frame_array[..., ::-1]
    if encoding == FrameEncoding.BGRA8:
        return frame_array[..., :3]
    if encoding == FrameEncoding.RGBA8:
        return frame_array[..., 2::-1]
    return None


def build_detectors(params: PerceptionParams, base_dir: Path | None) -> list[EventDetector]:
    """The detectors ``params`` turns on."""
    detectors: list[EventDetector] = []
    if params.motion is not None:
        detectors.append(MotionDetector(**params.motion.model_dump()))
    if params.scene_change is not None:
        detectors.append(SceneChangeDetector(**params.scene_change.model_dump()))
    if params.objects is not None:
        objects = params.objects
        field = "observers[].params.objects.model"
        path = resolve_user_path(objects.model, field=field)
        if not path.is_absolute() and base_dir is not None and not is_regular_file(path):
            path = base_dir / path
        path = require_user_file(path, field=field, what="model file")
        # Loaded only when asked for: the detector imports onnxruntime (the 'policy' extra).
        module = importlib.import_module("openral_runner.backends.gstreamer.objects_detector")
        detectors.append(
            module.make_objects_detector(
                str(path),
                labels=objects.labels,
                model_id=objects.model_id or path.stem,
                input_size=objects.input_size,
                score_threshold=objects.score_threshold,
                resize=objects.resize,
            )
        )
    if params.detector_manifest is not None:
        manifest_path = Path(params.detector_manifest)
        if not manifest_path.is_absolute() and base_dir is not None:
            manifest_path = base_dir / manifest_path
        factory = importlib.import_module("openral_runner.backends.gstreamer.detector_factory")
        manifest = RSkillManifest.from_yaml(manifest_path, field="observers[].params.detector_manifest")
        detectors.append(factory.build_manifest_detector(manifest)[0])
    if not detectors:
        raise ROSConfigError(
            "no detector is on",
            field="observers[].params",
            hint="set motion, scene_change, objects or detector_manifest",
        )
    return detectors


def build_publisher(params: PerceptionParams, *, robot_id: str, base_dir: Path | None) -> PerceptionEventPublisher:
    """The detectors and sinks ``params`` asks for, in a publisher (not started)."""
    detectors = build_detectors(params, base_dir)
    sinks: list[EventSink] = []
    if params.zenoh is not None:
        # Loaded only when asked for: the sink imports eclipse-zenoh (the 'remote' extra).
        events = importlib.import_module("openral_remote.events")
        sinks.append(events.ZenohEventSink(params.zenoh, params.robot or robot_id))
    if params.ros2:
        # Loaded only when asked for: the sink imports rclpy (a ROS 2 installation).
        ros2 = importlib.import_module("openral_runner.bridges.ros2_perception")
        sinks.append(ros2.Ros2EventSink())
    return PerceptionEventPublisher(detectors, sinks, rate_hz=params.rate_hz, burst=params.burst)


class PerceptionObserver(TickObserver):
    """Feeds the frames of each tick to a perception publisher (O(1) per camera on the tick thread).

    Building it loads the detectors (the model files are checked) but opens no session: the runner
    calls :meth:`start` when it activates.
    """

    def __init__(self, publisher: PerceptionEventPublisher, *, sensors: list[str] | None = None) -> None:
        self.publisher = publisher
        self.sensors = None if sensors is None else set(sensors)

    def start(self) -> None:
        """Start the detector worker and open the sinks (the Zenoh session listens from here on)."""
        self.publisher.start()

    @classmethod
    def from_config(
        cls, params: Mapping[str, Any], *, robot: Any, env: Any, base_dir: Path | None = None
    ) -> PerceptionObserver:
        """Plugin constructor (observer ``perception``); ``params`` are :class:`PerceptionParams`."""
        config = validate_model(PerceptionParams, dict(params), field_prefix="observers[].params")
        return cls(build_publisher(config, robot_id=robot.robot_id, base_dir=base_dir), sensors=config.sensors)

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        frames = None if world is None else world.image_frames
        if not frames:
            return
        for sensor_id, frame in frames.items():
            if (self.sensors is None or sensor_id in self.sensors) and frame.data is not None:
                pixels = bgr_view(frame.as_array(), frame.encoding)
                if pixels is not None:
                    self.publisher.submit(pixels, sensor_id, frame.stamp_ns)

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        return

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        return

    def close(self) -> None:
        self.publisher.stop()
