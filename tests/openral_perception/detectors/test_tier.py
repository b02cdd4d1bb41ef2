"""Detector tiers: which one a host has, and the ones this build refuses say what they need."""

from __future__ import annotations

import pytest

from openral_core import ROSConfigError
from openral_perception.detectors.tier import DetectorTier, require_runnable, select_tier


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


@pytest.mark.parametrize(
    ("nvinfer", "jetson", "tier"),
    [
        (False, False, DetectorTier.CPU_ONNX),
        (False, True, DetectorTier.NVMM_AGGREGATOR),
        (True, True, DetectorTier.NVINFER),
        (True, False, DetectorTier.NVINFER),
    ],
)
def test_nvinfer_wins_then_a_jetson_then_the_cpu(nvinfer, jetson, tier):
    assert select_tier(nvinfer=nvinfer, jetson=jetson) is tier
