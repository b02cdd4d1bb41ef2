"""The detector tier a host has: asked of its GStreamer (nvinfer), then of its platform (a Jetson)."""

from __future__ import annotations

import pytest

pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")

from openral_runner.backends.gstreamer import objects_detector
from openral_runner.backends.gstreamer.pipeline import Platform

DetectorTier = objects_detector.DetectorTier


@pytest.mark.parametrize(
    ("nvinfer", "platform", "tier"),
    [
        (False, Platform.CPU_ONLY, DetectorTier.CPU_ONNX),
        (False, Platform.NVIDIA_DESKTOP, DetectorTier.CPU_ONNX),
        (False, Platform.TEGRA, DetectorTier.NVMM_AGGREGATOR),
        (True, Platform.TEGRA, DetectorTier.NVINFER),
        (True, Platform.CPU_ONLY, DetectorTier.NVINFER),
    ],
)
def test_nvinfer_wins_then_a_jetson_then_the_cpu(
    monkeypatch: pytest.MonkeyPatch, nvinfer: bool, platform: Platform, tier: DetectorTier
) -> None:
    asked: list[str] = []
    monkeypatch.setattr(objects_detector, "inspect_element_present", lambda name: asked.append(name) or nvinfer)
    assert objects_detector.select_detector_tier(platform) is tier
    assert asked == ["nvinfer"]
