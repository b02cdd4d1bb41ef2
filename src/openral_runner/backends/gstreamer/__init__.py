"""GStreamer capture backend.

This package imports without ``gi``: it exposes the pure-Python pipeline builder and the
``backend_params`` model. The reader,
:class:`~openral_runner.backends.gstreamer.reader.GStreamerSensorReader`, lives in ``reader``
and needs the ``gstreamer`` extra and the system GStreamer libraries.
"""

from openral_runner.backends.gstreamer.params import GStreamerParams, settings_from_config
from openral_runner.backends.gstreamer.pipeline import (
    LEAKY_BRANCH_QUEUE,
    TEE_NAME,
    Codec,
    PipelineSpec,
    PixelFormat,
    Platform,
    Source,
    build_pipeline_string,
    detect_platform,
    ensure_appsink_name,
    inspect_element_present,
    leaky_branch,
    nvmm_convert_element,
)

__all__ = [
    "LEAKY_BRANCH_QUEUE",
    "TEE_NAME",
    "Codec",
    "GStreamerParams",
    "PipelineSpec",
    "PixelFormat",
    "Platform",
    "Source",
    "build_pipeline_string",
    "detect_platform",
    "ensure_appsink_name",
    "inspect_element_present",
    "leaky_branch",
    "nvmm_convert_element",
    "settings_from_config",
]
