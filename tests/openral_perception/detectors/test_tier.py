"""Detector tiers: the ones this build refuses say what they need."""

from __future__ import annotations

import pytest

from openral_core import ROSConfigError
from openral_perception.detectors.tier import DetectorTier, require_runnable


@pytest.mark.parametrize(
    ("tier", "need"),
    [
        (DetectorTier.NVINFER, "nvinfer"),
        (DetectorTier.NVMM_AGGREGATOR, "Jetson"),
        (DetectorTier.VLM_SIDECAR, "hub"),
        (DetectorTier.ZEROSHOT_HF, "Hugging Face"),
    ],
)
def test_tiers_that_need_hardware_say_what_they_need(tier, need):
    with pytest.raises(ROSConfigError, match=need) as refused:
        require_runnable(tier)
    assert refused.value.field == "manifest"


def test_the_cpu_tier_runs():
    require_runnable(DetectorTier.CPU_ONNX)
