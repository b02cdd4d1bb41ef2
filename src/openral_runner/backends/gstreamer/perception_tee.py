"""Re-exports at the path the specification fixed: the perception event publisher and numpy detectors, no tee.

The publisher lives in :mod:`openral_perception.publisher` and the detectors in
:mod:`openral_perception.detectors`; none of them needs GStreamer. The camera's event leg that
feeds a publisher (the tee branch ``enable_event_tee`` adds) is the reader's
(:mod:`openral_runner.backends.gstreamer.reader`).
"""

from openral_perception.detectors.base import EventDetector
from openral_perception.detectors.motion import MotionDetector
from openral_perception.detectors.scene_change import SceneChangeDetector
from openral_perception.frame import DetectorFrame
from openral_perception.publisher import (
    TOPIC_PREFIX,
    EventSink,
    OpenableEventSink,
    PerceptionEventPublisher,
    TokenBucket,
)

__all__ = [
    "TOPIC_PREFIX",
    "DetectorFrame",
    "EventDetector",
    "EventSink",
    "MotionDetector",
    "OpenableEventSink",
    "PerceptionEventPublisher",
    "SceneChangeDetector",
    "TokenBucket",
]
