"""The ONNX object detector at its specification path; it lives in :mod:`openral_perception.detectors.objects`.

Importing it loads onnxruntime (the ``policy`` extra), as the detector does.
"""

from openral_perception.detectors.objects import ObjectsDetector, make_objects_detector
from openral_perception.detectors.rtdetr import identify_rtdetr_outputs, postprocess_rtdetr
from openral_perception.detectors.tier import DetectorTier, select_detector_tier

__all__ = [
    "DetectorTier",
    "ObjectsDetector",
    "identify_rtdetr_outputs",
    "make_objects_detector",
    "postprocess_rtdetr",
    "select_detector_tier",
]
