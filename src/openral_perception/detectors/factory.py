"""From a ``kind: detector`` rSkill manifest to the detector it describes and the tier it runs on.

The manifest is read and its tier decided (:mod:`~openral_perception.detectors.objects_params`),
and a tier this build cannot run refused with what it needs, all before any model is loaded.
"""

from __future__ import annotations

from openral_perception.detectors.base import EventDetector
from openral_perception.detectors.objects_params import manifest_settings, manifest_tier
from openral_perception.detectors.tier import DetectorTier, require_runnable
from openral_rskill.manifest import RSkillManifest


def build_manifest_detector(
    manifest: RSkillManifest, *, onnx_path: str | None = None, tier: str | None = None
) -> tuple[EventDetector, DetectorTier]:
    """The detector a manifest describes and the tier it runs on.

    ``engine: zeroshot_hf`` and ``runtime: pytorch`` (an open-vocabulary VLM sidecar) need hub
    weights and PyTorch; ``runtime: tensorrt`` needs an NVIDIA GPU: each is refused naming what
    it needs, before anything is loaded. ``runtime: onnx`` runs on the CPU with ONNX Runtime.

    Raises:
        ROSConfigError: Not a detector manifest, no model, or a tier this machine cannot run.
        ROSDependencyMissing: onnxruntime is not installed (the ``policy`` extra).
    """
    chosen = manifest_tier(manifest, tier)
    require_runnable(chosen, field="manifest" if tier is None else "tier")
    settings = manifest_settings(manifest, onnx_path=onnx_path)
    # The ONNX detector imports onnxruntime: loaded here, once a manifest that runs on it is in hand.
    from openral_perception.detectors.objects import ObjectsDetector  # noqa: PLC0415

    return ObjectsDetector.from_settings(settings), chosen
