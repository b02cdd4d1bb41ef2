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
          zenoh: {listen: [tcp/0.0.0.0:7448]}
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import FrameEncoding, ROSConfigError, TickResult, WorldState
from openral_core.config import validate_model
from openral_remote.config import ZenohConfig
from openral_runner.backends.gstreamer.perception_tee import (
    EventDetector,
    EventSink,
    MotionDetector,
    PerceptionEventPublisher,
    SceneChangeDetector,
)
from openral_runner.observer import TickObserver


class MotionParams(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold: float = Field(default=25.0, ge=0, lt=255, description="Grey-level step that counts as a change.")
    cell: int = Field(default=8, ge=1, description="Cell size in pixels.")
    min_cell_fraction: float = Field(default=0.25, gt=0, le=1, description="Changed pixels that make a cell change.")
    min_cells: int = Field(default=2, ge=1, description="Changed cells that make an event.")


class SceneChangeParams(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    threshold: float = Field(default=0.5, gt=0, le=2, description="Chi-square distance (0–2) that is a change.")
    bins: int = Field(default=32, ge=2, le=256)


class ObjectsParams(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    model: str = Field(min_length=1, description="An ONNX detector with the RT-DETR signature.")
    labels: list[str] = Field(min_length=1, description="Class names, in the model's class order.")
    model_id: str | None = Field(default=None, description="Named in the events (default: the file's stem).")
    input_size: tuple[int, int] = Field(default=(640, 640), description="The model's (height, width).")
    score_threshold: float = Field(default=0.5, ge=0, le=1)
    resize: str = Field(default="stretch", description="stretch or letterbox (keep the aspect, pad).")


class PerceptionParams(BaseModel):
    """``params`` of the ``perception`` observer."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    sensors: list[str] | None = Field(default=None, description="Cameras to watch (default: every camera).")
    rate_hz: float = Field(default=5.0, gt=0, le=1000, description="Detections per second per camera and kind.")
    burst: int = Field(default=1, ge=1, le=100)
    motion: MotionParams | None = None
    scene_change: SceneChangeParams | None = None
    objects: ObjectsParams | None = None
    zenoh: ZenohConfig | None = Field(default=None, description="Publish events on Zenoh with this session.")
    robot: str | None = Field(default=None, description="Robot segment of the Zenoh keys (default: the robot id).")


def bgr_view(frame_array: np.ndarray, encoding: FrameEncoding) -> np.ndarray | None:
    """A BGR (or grey) view of a frame's pixels without copying; ``None`` for compressed or 16-bit frames."""
    if encoding in (FrameEncoding.BGR8, FrameEncoding.MONO8):
        return frame_array
    if encoding is FrameEncoding.RGB8:
        return frame_array[..., ::-1]
    if encoding is FrameEncoding.BGRA8:
        return frame_array[..., :3]
    if encoding is FrameEncoding.RGBA8:
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
        path = Path(objects.model)
        if not path.is_absolute() and base_dir is not None and not path.is_file():
            path = base_dir / path
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
    if not detectors:
        raise ROSConfigError(
            "no detector is on", field="observers[].params", hint="set motion, scene_change or objects"
        )
    return detectors


class PerceptionObserver(TickObserver):
    """Feeds the frames of each tick to a perception publisher (O(1) per camera on the tick thread)."""

    def __init__(self, publisher: PerceptionEventPublisher, *, sensors: list[str] | None = None) -> None:
        self.publisher = publisher
        self.sensors = None if sensors is None else set(sensors)
        publisher.start()

    @classmethod
    def from_config(
        cls, params: Mapping[str, Any], *, robot: Any, env: Any, base_dir: Path | None = None
    ) -> PerceptionObserver:
        """Plugin constructor (observer ``perception``); ``params`` are :class:`PerceptionParams`."""
        config = validate_model(PerceptionParams, dict(params), field_prefix="observers[].params")
        detectors = build_detectors(config, base_dir)
        sinks: list[EventSink] = []
        if config.zenoh is not None:
            # Loaded only when asked for: the sink imports eclipse-zenoh (the 'remote' extra).
            events = importlib.import_module("openral_remote.events")
            sinks.append(events.ZenohEventSink(config.zenoh, config.robot or robot.robot_id))
        publisher = PerceptionEventPublisher(detectors, sinks, rate_hz=config.rate_hz, burst=config.burst)
        return cls(publisher, sensors=config.sensors)

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
