"""A ``kind: detector`` manifest run on a branch of a live pipeline's tee."""

from __future__ import annotations

import importlib
import threading
from pathlib import Path

import pytest

from openral_core import ROSConfigError
from openral_rskill.manifest import RSkillManifest

pytestmark = pytest.mark.gstreamer

pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")
pytest.importorskip(
    "gi", reason="needs GStreamer and PyGObject: run scripts/install-system-deps.sh, then uv sync --extra gstreamer"
)
try:
    runner_module = importlib.import_module("openral_runner.backends.gstreamer.detector_runner")
except ROSConfigError as exc:  # gi present, GStreamer typelibs missing
    pytest.skip(f"GStreamer introspection data missing: {exc}", allow_module_level=True)

from gi.repository import Gst  # noqa: E402

from openral_runner.backends.gstreamer.pipeline import TEE_NAME, leaky_branch  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]


def _manifest(tmp_path: Path) -> RSkillManifest:
    (tmp_path / "cube_detector.onnx").write_bytes((ROOT / "models" / "cube_detector.onnx").read_bytes())
    path = tmp_path / "cube.rskill.yaml"
    path.write_text(
        "name: cube_detector\nkind: detector\nlicense: Apache-2.0\n"
        "detector:\n  model: cube_detector.onnx\n  labels: [cube]\n  score_threshold: 0.5\n",
        encoding="utf-8",
    )
    return RSkillManifest.from_yaml(path)


def test_the_detector_runs_on_a_live_branch_and_finds_the_magenta_ball(tmp_path):
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

    runner = runner_module.DetectorRunner(pipeline, _manifest(tmp_path), sensor_id="front", on_detection=on_detection)
    assert pipeline.set_state(Gst.State.PLAYING) != Gst.StateChangeReturn.FAILURE
    try:
        # The branch joins a running pipeline, as it would on a robot: wait until it is running.
        change, state, _pending = pipeline.get_state(10 * Gst.SECOND)
        assert state == Gst.State.PLAYING, f"the pipeline did not start: {change.value_nick}"
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
