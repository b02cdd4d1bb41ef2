"""From a ``kind: detector`` manifest or the ``objects`` params to the ONNX detector, tiers refused before loading."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from openral_core import ROSConfigError
from openral_perception.detectors.factory import build_manifest_detector
from openral_perception.detectors.objects_params import ObjectsParams, objects_settings
from openral_rskill.manifest import RSkillManifest

ROOT = Path(__file__).resolve().parents[3]


def _manifest(tmp_path: Path, **detector: object) -> RSkillManifest:
    text = (
        "name: cube_detector\nkind: detector\nlicense: Apache-2.0\n"
        "detector:\n  model: cube_detector.onnx\n  labels: [cube]\n"
        + "".join(f"  {key}: {value}\n" for key, value in detector.items())
    )
    (tmp_path / "cube_detector.onnx").write_bytes((ROOT / "models" / "cube_detector.onnx").read_bytes())
    path = tmp_path / "cube.rskill.yaml"
    path.write_text(text, encoding="utf-8")
    return RSkillManifest.from_yaml(path)


def test_a_detector_manifest_builds_the_cpu_detector_with_its_model_beside_it(tmp_path):
    pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")
    detector, tier = build_manifest_detector(_manifest(tmp_path, score_threshold=0.4))
    assert tier.value == "cpu_onnx"
    assert detector.labels == ["cube"]
    assert detector.model_id == "cube_detector"
    assert detector.score_threshold == 0.4


@pytest.mark.parametrize(
    ("setting", "need"),
    [
        ({"runtime": "tensorrt"}, "nvinfer"),
        ({"runtime": "pytorch"}, "hub"),
        ({"engine": "zeroshot_hf"}, "Hugging Face"),
    ],
)
def test_tiers_that_need_more_than_this_machine_say_what(tmp_path, setting, need):
    with pytest.raises(ROSConfigError, match=need):
        build_manifest_detector(_manifest(tmp_path, **setting))


def test_kinds_carry_their_own_block_only():
    with pytest.raises(ValidationError, match="needs 'detector'"):
        RSkillManifest(name="d", kind="detector", license="MIT")
    with pytest.raises(ValidationError, match="has no skill"):
        RSkillManifest(name="d", kind="detector", license="MIT", skill="hello", detector={"labels": ["x"]})
    with pytest.raises(ValidationError, match="needs 'skill'"):
        RSkillManifest(name="p", license="MIT")
    policy = RSkillManifest(name="p", license="MIT", skill="hello")
    with pytest.raises(ROSConfigError, match="not a detector"):
        build_manifest_detector(policy)


def test_the_objects_params_name_a_model_and_labels_or_a_manifest(tmp_path):
    with pytest.raises(ValidationError, match="exactly one of model"):
        ObjectsParams()
    with pytest.raises(ValidationError, match="labels"):
        ObjectsParams(model="m.onnx")
    with pytest.raises(ValidationError, match="labels come from the manifest"):
        ObjectsParams(manifest="cube.rskill.yaml", labels=["cube"])
    manifest = _manifest(tmp_path, score_threshold=0.3)
    from_manifest = objects_settings(ObjectsParams(manifest=manifest.source), base_dir=None)
    assert (from_manifest.model, from_manifest.labels) == (tmp_path / "cube_detector.onnx", ["cube"])
    assert (from_manifest.model_id, from_manifest.score_threshold) == ("cube_detector", 0.3)
    from_model = objects_settings(ObjectsParams(model="cube_detector.onnx", labels=["cube"]), base_dir=tmp_path)
    assert (from_model.model, from_model.model_id) == (tmp_path / "cube_detector.onnx", "cube_detector")


def test_a_model_file_that_is_missing_is_named_as_the_model(tmp_path):
    with pytest.raises(ROSConfigError, match=r"^model: model file not found"):
        objects_settings(ObjectsParams(model="missing.onnx", labels=["x"]), base_dir=tmp_path)
