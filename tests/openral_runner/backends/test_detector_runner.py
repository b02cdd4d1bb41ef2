"""A ``kind: detector`` manifest: built without GStreamer, then run on a branch of a live pipeline's tee."""

from __future__ import annotations

import importlib
import threading
from pathlib import Path

import pytest
from pydantic import ValidationError

from openral_core import ROSConfigError
from openral_rskill.manifest import RSkillManifest

pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")

from openral_runner.backends.gstreamer.detector_factory import build_manifest_detector

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


@pytest.mark.gstreamer
def test_the_detector_runs_on_a_live_branch_and_finds_the_magenta_ball(tmp_path):
    pytest.importorskip(
        "gi", reason="needs GStreamer and PyGObject: run scripts/install-system-deps.sh, then uv sync --extra gstreamer"
    )
    try:
        runner_module = importlib.import_module("openral_runner.backends.gstreamer.detector_runner")
    except ROSConfigError as exc:
        pytest.skip(f"GStreamer introspection data missing: {exc}")
    from gi.repository import Gst  # noqa: PLC0415

    from openral_runner.backends.gstreamer.pipeline import TEE_NAME, leaky_branch  # noqa: PLC0415

    pipeline = Gst.parse_launch(
        "videotestsrc is-live=true pattern=ball foreground-color=0xffd040d0 background-color=0xff202840 "
        "! video/x-raw,format=BGR,width=160,height=120,framerate=30/1 "
        f"! tee name={TEE_NAME} allow-not-linked=true " + leaky_branch("fakesink sync=false")
    )
    found = []
    seen = threading.Event()

    def on_detection(metadata) -> None:
        found.append(metadata)
        seen.set()

    runner = runner_module.DetectorRunner(
        pipeline, _manifest(tmp_path, score_threshold=0.5), sensor_id="front", on_detection=on_detection
    )
    assert pipeline.set_state(Gst.State.PLAYING) != Gst.StateChangeReturn.FAILURE
    try:
        runner.start()
        assert seen.wait(10), f"no detection after {runner.frames} frames ({runner.errors} errors)"
    finally:
        runner.stop()
        runner.stop()  # idempotent
        pipeline.set_state(Gst.State.NULL)
    box = found[0].detections[0].box
    assert found[0].detections[0].label == "cube"
    assert 0 < box.x1 - box.x0 < 80  # the ball, not the frame
    assert runner.tees.branch_count == 0
