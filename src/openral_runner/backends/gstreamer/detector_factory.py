"""From a ``kind: detector`` rSkill manifest to a running detector, without GStreamer (so it is testable anywhere)."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from openral_core import ROSConfigError
from openral_rskill.manifest import RSkillManifest


def _tier(name: str) -> Any:
    return importlib.import_module("openral_runner.backends.gstreamer.objects_detector").DetectorTier(name)


def model_path(manifest: RSkillManifest, onnx_path: str | None) -> Path:
    """The detector's model: ``onnx_path`` when given, else the manifest's ``detector.model`` (beside the manifest).

    Raises:
        ROSConfigError: Neither names a model.
    """
    detector = manifest.detector
    assert detector is not None
    if onnx_path is not None:
        return Path(onnx_path)
    if detector.model is None:
        raise ROSConfigError(
            f"detector {manifest.name!r} names no model", field="detector.model", hint="give a .onnx path"
        )
    path = Path(detector.model)
    if not path.is_absolute() and manifest.path is not None:
        path = manifest.path.parent / path
    return path


def build_manifest_detector(
    manifest: RSkillManifest, *, onnx_path: str | None = None, tier: str | None = None
) -> tuple[Any, Any]:
    """The detector a manifest describes and the tier it runs on.

    ``engine: zeroshot_hf`` and ``runtime: pytorch`` (an open-vocabulary VLM sidecar) need hub
    weights and PyTorch; ``runtime: tensorrt`` needs an NVIDIA GPU: each is refused naming what
    it needs. ``runtime: onnx`` runs on the CPU with ONNX Runtime.

    Raises:
        ROSConfigError: Not a detector manifest, no model, or a tier this machine cannot run.
    """
    detector = manifest.detector
    if manifest.kind != "detector" or detector is None:
        raise ROSConfigError(
            f"{manifest.name!r} is a {manifest.kind} manifest, not a detector", field="kind", hint="kind: detector"
        )
    objects = importlib.import_module("openral_runner.backends.gstreamer.objects_detector")
    if detector.engine == "zeroshot_hf":
        chosen = objects.DetectorTier.ZEROSHOT_HF
    elif detector.runtime == "pytorch":
        chosen = objects.DetectorTier.VLM_SIDECAR
    elif detector.runtime == "tensorrt":
        chosen = objects.DetectorTier.NVINFER
    else:
        chosen = objects.DetectorTier(tier) if tier is not None else objects.DetectorTier.CPU_ONNX
    built = objects.make_objects_detector(
        str(model_path(manifest, onnx_path)) if chosen is objects.DetectorTier.CPU_ONNX else "",
        labels=detector.labels,
        model_id=manifest.name,
        tier=chosen,
        input_size=tuple(detector.input_size),
        score_threshold=detector.score_threshold,
        resize=detector.resize,
    )
    return built, chosen
