"""``DetectorTier``: where an object detector runs, and what the tiers this build cannot run need.

Light on purpose (no onnxruntime, no GStreamer): a manifest's tier is decided, and refused with
what it needs, before any model is loaded.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable
from enum import StrEnum
from pathlib import Path

from openral_core import ROSConfigError

_INSPECT_TIMEOUT_S = 5.0


class DetectorTier(StrEnum):
    """Where an object detector runs."""

    CPU_ONNX = "cpu_onnx"
    NVINFER = "nvinfer"
    NVMM_AGGREGATOR = "nvmm_aggregator"
    VLM_SIDECAR = "vlm_sidecar"
    ZEROSHOT_HF = "zeroshot_hf"


TIER_NEEDS: dict[DetectorTier, str] = {
    DetectorTier.NVINFER: "DeepStream's nvinfer element and an NVIDIA GPU",
    DetectorTier.NVMM_AGGREGATOR: "a Jetson (NVMM buffers), TensorRT and cuda-python",
    DetectorTier.VLM_SIDECAR: "an open-vocabulary VLM sidecar and its weights from a model hub",
    DetectorTier.ZEROSHOT_HF: "PyTorch, transformers and zero-shot detector weights from the Hugging Face hub",
}
"""What each tier other than the CPU needs (none of it ships with openral)."""


def require_runnable(tier: DetectorTier, *, field: str = "manifest") -> None:
    """Accept the CPU tier; refuse any other, saying what it needs.

    Args:
        tier: The tier asked for.
        field: What asked for it (a detector manifest, or an explicit ``tier`` argument), for the error.

    Raises:
        ROSConfigError: A tier this build cannot run.
    """
    if tier is not DetectorTier.CPU_ONNX:
        raise ROSConfigError(
            f"the {tier.value} detector tier needs {TIER_NEEDS[tier]}; openral runs ONNX detectors on the CPU",
            field=field,
            hint="use a detector manifest with runtime: onnx (the cpu_onnx tier)",
        )


def select_detector_tier(
    *, has_nvinfer: Callable[[], bool] | None = None, on_tegra: Callable[[], bool] | None = None
) -> DetectorTier:
    """The fastest tier this machine has: ``nvinfer`` where DeepStream is installed, NVMM on a Jetson, else the CPU."""
    nvinfer = has_nvinfer or (lambda: _gst_has("nvinfer"))
    tegra = on_tegra or (lambda: Path("/etc/nv_tegra_release").exists())
    if nvinfer():
        return DetectorTier.NVINFER
    if tegra():
        return DetectorTier.NVMM_AGGREGATOR
    return DetectorTier.CPU_ONNX


def _gst_has(element: str) -> bool:
    """Whether the host's GStreamer has ``element`` (``gst-inspect-1.0 --exists``; no ``gi`` needed)."""
    tool = shutil.which("gst-inspect-1.0")
    if tool is None:
        return False
    try:
        proc = subprocess.run([tool, "--exists", element], capture_output=True, timeout=_INSPECT_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0
