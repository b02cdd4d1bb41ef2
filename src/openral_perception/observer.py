"""``perception`` observer: event detectors on the camera frames the runner already has.

The tick only hands each selected camera's frame (a reference, no copy) to a
:class:`~openral_perception.publisher.PerceptionEventPublisher`; its worker runs the detectors,
rate-limited per camera and kind, and publishes the events on Zenoh
(``openral/<robot>/perception/<kind>``, with ``zenoh:`` set), on ROS 2 (``ros2: true``) and in
telemetry.

.. code-block:: yaml

    observers:
      - id: perception
        params:
          rate_hz: 5
          detectors:
            - {kind: motion, params: {threshold: 25}}
            - {kind: scene_change, params: {threshold: 0.5}}
            - {kind: objects, params: {model: models/cube_detector.onnx, labels: [cube]}}
          zenoh: {listen: [tcp/127.0.0.1:7448]}
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from openral_core import ObserverContext, ROSConfigError, TickResult, WorldState
from openral_core.config import validate_model
from openral_observability.observer import TickObserver
from openral_perception.detectors.base import EventDetector
from openral_perception.detectors.registry import DETECTOR_REGISTRY, build_detector
from openral_perception.frame import is_viewable
from openral_perception.params import PerceptionParams
from openral_perception.publisher import EventSink, PerceptionEventPublisher

PARAMS_FIELD = "observers[].params"


def build_detectors(
    params: PerceptionParams, base_dir: Path | None, *, field: str = PARAMS_FIELD
) -> list[EventDetector]:
    """The detectors ``params`` configure, each built by its kind's class (see ``openral.detectors``).

    Raises:
        ROSConfigError: No detector, an unknown kind (the known ones listed), or a wrong parameter
            (named as ``<field>.detectors[<i>].params.<key>``).
    """
    entries = params.detector_entries()
    if not entries:
        raise ROSConfigError(
            "no detector is on",
            field=field,
            hint=f"list detectors: [{{kind: ..., params: {{...}}}}] with kinds from {', '.join(DETECTOR_REGISTRY)}",
        )
    return [build_detector(entry, base_dir=base_dir, field=field) for entry in entries]


def build_publisher(
    params: PerceptionParams, *, robot_id: str, base_dir: Path | None, field: str = PARAMS_FIELD
) -> PerceptionEventPublisher:
    """The detectors and sinks ``params`` asks for, in a publisher (not started: no sink is open yet)."""
    detectors = build_detectors(params, base_dir, field=field)
    sinks: list[EventSink] = []
    if params.zenoh is not None:
        # Loaded only when asked for: the sink imports eclipse-zenoh (the 'remote' extra).
        from openral_perception.sinks.zenoh import ZenohEventSink  # noqa: PLC0415

        sinks.append(ZenohEventSink(params.zenoh, params.robot or robot_id))
    if params.ros2:
        # Loaded only when asked for: the sink imports rclpy (a ROS 2 installation).
        from openral_perception.sinks.ros2 import Ros2EventSink  # noqa: PLC0415

        sinks.append(Ros2EventSink())
    return PerceptionEventPublisher(detectors, sinks, rate_hz=params.rate_hz, burst=params.burst)


class PerceptionObserver(TickObserver):
    """Feeds the frames of each tick to a perception publisher (O(1) per camera on the tick thread).

    Building it loads the detectors (the model files are checked) but opens no session: the runner
    calls :meth:`start` when it activates. Frames a detector cannot look at (compressed, 16-bit
    depth) are passed over.

    Args:
        publisher: Runs the detectors and owns the sinks.
        sensors: The cameras to watch (``None``: every camera of the world state).
    """

    def __init__(self, publisher: PerceptionEventPublisher, *, sensors: list[str] | None = None) -> None:
        self.publisher = publisher
        self.sensors = None if sensors is None else set(sensors)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], context: ObserverContext) -> PerceptionObserver:
        """Plugin constructor (observer ``perception``); ``params`` are :class:`~.params.PerceptionParams`."""
        config = validate_model(PerceptionParams, dict(params), field_prefix=PARAMS_FIELD)
        return cls(
            build_publisher(config, robot_id=context.robot_id, base_dir=context.base_dir), sensors=config.sensors
        )

    def start(self) -> None:
        """Open the sinks and start the detector worker (the Zenoh session listens from here on)."""
        self.publisher.start()

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        frames = None if world is None else world.image_frames
        if not frames:
            return
        for sensor_id, frame in frames.items():
            if (self.sensors is None or sensor_id in self.sensors) and is_viewable(frame):
                self.publisher.submit(frame)

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        return

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        return

    def close(self) -> None:
        """Let the worker finish the frames waiting, then close the sinks."""
        self.publisher.close()
