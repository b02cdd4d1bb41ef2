"""``DetectorTier``: where an object detector runs, which one a host has, and what the tiers this build cannot run need.

Light on purpose (no onnxruntime, no GStreamer): a manifest's tier is decided, and refused with
what it needs, before any model is loaded.
"""

from __future__ import annotations

from enum import StrEnum

from openral_core import ROSConfigError


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


def select_tier(*, nvinfer: bool, jetson: bool) -> DetectorTier:
    """The fastest tier of a host that has DeepStream's ``nvinfer`` element, is a Jetson, or neither.

    ``nvinfer`` wins over a Jetson's NVMM buffers (DeepStream runs on Jetsons too); without either
    the host has the CPU. Asking the host is the caller's (its GStreamer, its platform).
    """
    if nvinfer:
        return DetectorTier.NVINFER
    if jetson:
        return DetectorTier.NVMM_AGGREGATOR
    return DetectorTier.CPU_ONNX
