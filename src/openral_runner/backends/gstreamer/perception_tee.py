"""Re-exports at the path the specification fixed: the perception event publisher and numpy detectors, no tee.

The detectors here take a frame the way an appsink hands it over (``detect(frame_bgr, width,
height, sensor_id)``); they live in :mod:`openral_perception.detectors.buffers`, over the same
frame seam as the registered kinds. The publisher lives in :mod:`openral_perception.publisher`;
none of them needs GStreamer. The camera's event leg that feeds a publisher (the tee branch
``enable_event_tee`` adds) is the reader's (:mod:`openral_runner.backends.gstreamer.reader`).
"""

from openral_perception.detectors.buffers import BufferEventDetector as EventDetector
from openral_perception.detectors.buffers import BufferMotionDetector as MotionDetector
from openral_perception.detectors.buffers import BufferSceneChangeDetector as SceneChangeDetector
from openral_perception.detectors.buffers import FrameBuffer
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
    "FrameBuffer",
    "MotionDetector",
    "OpenableEventSink",
    "PerceptionEventPublisher",
    "SceneChangeDetector",
    "TokenBucket",
]
