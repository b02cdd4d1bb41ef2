"""The ``objects`` detector's parameters and settings: light (no onnxruntime), so a deployment is checked first.

:class:`ObjectsParams` is what a deployment writes (an ONNX ``model`` and its ``labels``, or a
detector ``manifest``); :class:`ObjectsSettings` is what the detector is built with, a checked
model file and how to read it, whichever of the two named it. A manifest's tier is decided here,
and a tier this build cannot run is refused with what it needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, model_validator

from openral_core import ROSConfigError
from openral_core.config_files import expand_user_path, is_regular_file, require_user_file
from openral_core.perception import ModelInputSize
from openral_perception.detectors.tier import DetectorTier, require_runnable
from openral_rskill.manifest import DetectorContract, RSkillManifest


class ObjectsParams(BaseModel):
    """``params`` of the ``objects`` detector: an ONNX ``model`` and its ``labels``, or a detector ``manifest``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    model: str | None = Field(
        default=None, min_length=1, description="An ONNX model with the RT-DETR signature, relative to the deployment."
    )
    manifest: str | None = Field(
        default=None,
        min_length=1,
        description="A kind: detector rSkill manifest (instead of model and the rest), relative to the deployment.",
    )
    labels: list[str] | None = Field(default=None, min_length=1, description="Class names, in the model's order.")
    model_id: str | None = Field(default=None, description="Named in the events (default: the file's stem).")
    input_size: ModelInputSize = Field(default=(640, 640), description="The model's (height, width).")
    score_threshold: float = Field(default=0.5, ge=0, le=1)
    resize: Literal["stretch", "letterbox"] = Field(default="stretch", description="letterbox keeps the aspect.")

    @model_validator(mode="after")
    def _model_or_manifest(self) -> Self:
        if (self.model is None) == (self.manifest is None):
            raise ValueError("set exactly one of model (an .onnx file, with labels) or manifest (a detector rSkill)")
        if self.manifest is not None:
            extra = sorted(self.model_fields_set - {"manifest"})
            if extra:
                raise ValueError(f"{', '.join(extra)} come from the manifest; set them there, or give model instead")
        elif self.labels is None:
            raise ValueError("a model needs its labels: the class names, in the model's class order")
        return self


@dataclass(frozen=True)
class ObjectsSettings:
    """What the ONNX detector is built with: a checked model file and how to read it."""

    model: Path
    labels: list[str]
    model_id: str
    input_size: tuple[int, int] = (640, 640)
    score_threshold: float = 0.5
    resize: Literal["stretch", "letterbox"] = "stretch"


def objects_settings(params: ObjectsParams, *, base_dir: Path | None = None) -> ObjectsSettings:
    """The settings ``params`` ask for, from the model named or the manifest's.

    A relative manifest path is taken from ``base_dir`` (the deployment's folder); a relative model
    path from the working directory when a file is there, else from ``base_dir``.

    Raises:
        ROSConfigError: The model or manifest is not a readable file (naming ``model`` or
            ``manifest``), or the manifest is not a detector this build can run.
    """
    if params.manifest is not None:
        path = require_user_file(params.manifest, base_dir, field="manifest", what="detector manifest")
        manifest = RSkillManifest.from_yaml(path, field="manifest")
        require_runnable(manifest_tier(manifest))
        return manifest_settings(manifest)
    assert params.model is not None  # the model's validator: no manifest, so a model
    assert params.labels is not None  # ... and its labels
    path = _user_file(params.model, base_dir, field="model", what="model file")
    return ObjectsSettings(
        model=path,
        labels=list(params.labels),
        model_id=params.model_id or path.stem,
        input_size=params.input_size,
        score_threshold=params.score_threshold,
        resize=params.resize,
    )


def _user_file(value: str, base_dir: Path | None, *, field: str, what: str) -> Path:
    path = expand_user_path(value, field=field)
    if not path.is_absolute() and base_dir is not None and not is_regular_file(path):
        path = base_dir / path
    return require_user_file(path, field=field, what=what)


def model_path(manifest: RSkillManifest, onnx_path: str | None) -> Path:
    """The detector's model: ``onnx_path`` when given, else the manifest's ``detector.model`` (beside the manifest).

    Raises:
        ROSConfigError: Neither names a model.
    """
    detector = _contract(manifest)
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


def manifest_tier(manifest: RSkillManifest, tier: str | None = None) -> DetectorTier:
    """Where a detector manifest runs: its engine or runtime decides when it needs more than a CPU, else ``tier``.

    Raises:
        ROSConfigError: Not a detector manifest, or an unknown ``tier``.
    """
    detector = _contract(manifest)
    if detector.engine == "zeroshot_hf":
        return DetectorTier.ZEROSHOT_HF
    if detector.runtime == "pytorch":
        return DetectorTier.VLM_SIDECAR
    if detector.runtime == "tensorrt":
        return DetectorTier.NVINFER
    if tier is None:
        return DetectorTier.CPU_ONNX
    try:
        return DetectorTier(tier)
    except ValueError as exc:
        known = ", ".join(t.value for t in DetectorTier)
        raise ROSConfigError(f"unknown detector tier {tier!r}; known: {known}", field="tier") from exc


def manifest_settings(manifest: RSkillManifest, *, onnx_path: str | None = None) -> ObjectsSettings:
    """The ONNX detector's settings from a detector manifest (its name is the events' ``model_id``)."""
    detector = _contract(manifest)
    return ObjectsSettings(
        model=model_path(manifest, onnx_path),
        labels=list(detector.labels),
        model_id=manifest.name,
        input_size=detector.input_size,
        score_threshold=detector.score_threshold,
        resize=detector.resize,
    )


def _contract(manifest: RSkillManifest) -> DetectorContract:
    """The manifest's detector block; a manifest of another kind is refused."""
    detector = manifest.detector
    if manifest.kind != "detector" or detector is None:
        raise ROSConfigError(
            f"{manifest.name!r} is a {manifest.kind} manifest, not a detector", field="kind", hint="kind: detector"
        )
    return detector
