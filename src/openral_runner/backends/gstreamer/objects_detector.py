"""The ONNX object detector at its specification path (it lives in :mod:`openral_perception.detectors.objects`),
and the choice of tier, which asks the host's GStreamer.

Importing it loads onnxruntime (the ``policy`` extra), as the detector does.
"""

from openral_perception.detectors.objects import ObjectsDetector, make_objects_detector
from openral_perception.detectors.rtdetr import identify_rtdetr_outputs, postprocess_rtdetr
from openral_perception.detectors.tier import DetectorTier
from openral_runner.backends.gstreamer.pipeline import Platform, detect_platform, inspect_element_present


def select_detector_tier(platform: Platform | None = None) -> DetectorTier:
    """The fastest tier this host has: ``nvinfer`` where DeepStream is installed (whatever ``platform``
    says), NVMM on a Jetson, else the CPU."""
    if inspect_element_present("nvinfer"):
        return DetectorTier.NVINFER
    if (platform or detect_platform()) is Platform.TEGRA:
        return DetectorTier.NVMM_AGGREGATOR
    return DetectorTier.CPU_ONNX


__all__ = [
    "DetectorTier",
    "ObjectsDetector",
    "identify_rtdetr_outputs",
    "make_objects_detector",
    "postprocess_rtdetr",
    "select_detector_tier",
]
