"""The ONNX object detector at its specification path (it lives in :mod:`openral_perception.detectors.objects`),
and the tier this host has, asked of its GStreamer.

``ObjectsDetector(onnx_path, *, labels, model_id, input_size=(640, 640), score_threshold=0.5,
device="cpu")`` takes an appsink's frame, ``detect(frame_bgr, width, height, sensor_id)``.
Importing this module loads onnxruntime (the ``policy`` extra), as the detector does.
"""

from openral_perception.detectors.objects import ObjectsDetector, make_objects_detector
from openral_perception.detectors.rtdetr import identify_rtdetr_outputs, postprocess_rtdetr
from openral_perception.detectors.tier import DetectorTier, select_tier
from openral_runner.backends.gstreamer.pipeline import Platform, detect_platform, inspect_element_present


def select_detector_tier(platform: Platform | None = None) -> DetectorTier:
    """The fastest tier this host has (:func:`~openral_perception.detectors.tier.select_tier`): ``nvinfer``
    where DeepStream is installed (whatever ``platform`` says), NVMM on a Jetson, else the CPU."""
    return select_tier(
        nvinfer=inspect_element_present("nvinfer"), jetson=(platform or detect_platform()) is Platform.TEGRA
    )


__all__ = [
    "DetectorTier",
    "ObjectsDetector",
    "identify_rtdetr_outputs",
    "make_objects_detector",
    "postprocess_rtdetr",
    "select_detector_tier",
]
