"""The perception settings at their specification path; they live in :mod:`openral_perception.params`."""

from openral_perception.detectors.motion import MotionParams
from openral_perception.detectors.objects_params import ObjectsParams
from openral_perception.detectors.scene_change import SceneChangeParams
from openral_perception.params import DEFAULT_EVENT_LISTEN, DetectorConfig, PerceptionParams

__all__ = [
    "DEFAULT_EVENT_LISTEN",
    "DetectorConfig",
    "MotionParams",
    "ObjectsParams",
    "PerceptionParams",
    "SceneChangeParams",
]
