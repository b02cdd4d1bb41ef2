"""Detector tiers: the fastest one a machine has, and the ones this build refuses with what they need."""

from __future__ import annotations

import pytest

from openral_core import ROSConfigError
from openral_perception.detectors.tier import DetectorTier, require_runnable, select_detector_tier


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


def test_the_cpu_runs_and_the_fastest_tier_present_is_selected():
    require_runnable(DetectorTier.CPU_ONNX)
    assert select_detector_tier(has_nvinfer=lambda: False, on_tegra=lambda: False) is DetectorTier.CPU_ONNX
    assert select_detector_tier(has_nvinfer=lambda: False, on_tegra=lambda: True) is DetectorTier.NVMM_AGGREGATOR
    assert select_detector_tier(has_nvinfer=lambda: True, on_tegra=lambda: True) is DetectorTier.NVINFER
