"""The specification's module paths still name perception's parts, and its detectors keep its contract.

The detectors at ``openral_runner.backends.gstreamer.perception_tee`` are called as the
specification says: ``MotionDetector(*, threshold=0.02, downsample=1)`` (BT.601 luma, mean
absolute change), ``SceneChangeDetector(*, threshold=0.5)`` (32-bin grey histograms,
``chisqr_alt`` distance), ``detect(frame_bgr, width, height, sensor_id)`` on an appsink's BGR
buffer, ``summarise(metadata)`` one line for people. So is the object detector at
``openral_runner.backends.gstreamer.objects_detector``: ``ObjectsDetector(onnx_path, *, labels,
model_id, input_size=(640, 640), score_threshold=0.5, device="cpu")``, its ``summarise`` counting
each label as ``"Nx label"``.
"""

from __future__ import annotations

import importlib
import inspect
from pathlib import Path

import numpy as np
import pytest

from openral_core import ROSConfigError, SensorFrame
from openral_core.perception import ObjectsMetadata, PixelBox

LIGHT_PATHS = [
    ("openral_runner.perception", "openral_perception.observer", ["PerceptionObserver", "build_publisher"]),
    ("openral_runner.perception_params", "openral_perception.params", ["PerceptionParams", "DEFAULT_EVENT_LISTEN"]),
    (
        "openral_runner.backends.gstreamer.perception_tee",
        "openral_perception.publisher",
        ["PerceptionEventPublisher", "TokenBucket", "TOPIC_PREFIX", "EventSink"],
    ),
    (
        "openral_runner.backends.gstreamer.detector_factory",
        "openral_perception.detectors.factory",
        ["build_manifest_detector"],
    ),
    (
        "openral_runner.backends.gstreamer.detector_factory",
        "openral_perception.detectors.objects_params",
        ["model_path"],
    ),
    ("openral_runner.backends.reward", "openral_perception.reward", ["Frame", "RollingFrameBuffer", "trend"]),
    ("openral_runner.backends.reward.frames", "openral_perception.reward.frames", ["RollingFrameBuffer"]),
    ("openral_runner.world_cloud_bridge", "openral_perception.world_cloud", ["encode_world_cloud_png"]),
]


@pytest.mark.parametrize(("spec_path", "home", "names"), LIGHT_PATHS)
def test_the_specification_paths_name_the_same_objects(spec_path: str, home: str, names: list[str]) -> None:
    spec_module, home_module = importlib.import_module(spec_path), importlib.import_module(home)
    for name in names:
        assert getattr(spec_module, name) is getattr(home_module, name), name
        assert name in spec_module.__all__


def test_the_heavy_specification_paths_name_the_same_objects():
    pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")
    pytest.importorskip("zenoh", reason="needs the 'remote' extra")
    objects = importlib.import_module("openral_runner.backends.gstreamer.objects_detector")
    client = importlib.import_module("openral_runner.backends.reward.client")
    from openral_perception.detectors.objects import ObjectsDetector  # noqa: PLC0415
    from openral_perception.reward.client import RewardMonitor  # noqa: PLC0415

    assert objects.ObjectsDetector is ObjectsDetector
    assert client.RewardMonitor is RewardMonitor
    from openral_perception.detectors import rtdetr  # noqa: PLC0415

    assert objects.identify_rtdetr_outputs is rtdetr.identify_rtdetr_outputs
    assert objects.postprocess_rtdetr is rtdetr.postprocess_rtdetr
    assert {"ObjectsDetector", "make_objects_detector", "select_detector_tier", "DetectorTier"} <= set(objects.__all__)


def test_the_specification_detectors_live_in_perception():
    tee = importlib.import_module("openral_runner.backends.gstreamer.perception_tee")
    buffers = importlib.import_module("openral_perception.detectors.buffers")
    assert tee.EventDetector is buffers.BufferEventDetector
    assert tee.MotionDetector is buffers.BufferMotionDetector
    assert tee.SceneChangeDetector is buffers.BufferSceneChangeDetector
    assert {"EventDetector", "MotionDetector", "SceneChangeDetector", "TOPIC_PREFIX"} <= set(tee.__all__)


# The detectors as the specification describes them, through its path.

H, W = 24, 32


def tee():
    return importlib.import_module("openral_runner.backends.gstreamer.perception_tee")


def bgr(level: int | tuple[int, int, int], height: int = H, width: int = W) -> np.ndarray:
    return np.broadcast_to(np.asarray(level, dtype=np.uint8), (height, width, 3)).copy()


FORMS = {
    "bytes": lambda a: a.tobytes(),
    "bytearray": lambda a: bytearray(a.tobytes()),
    "memoryview": lambda a: memoryview(a.tobytes()),
    "flat ndarray": lambda a: a.reshape(-1),
    "shaped ndarray": lambda a: a,
}


def test_the_event_detector_protocol_has_the_specification_signature():
    detect = inspect.signature(tee().EventDetector.detect)
    assert list(detect.parameters) == ["self", "frame_bgr", "width", "height", "sensor_id"]
    assert list(inspect.signature(tee().EventDetector.summarise).parameters) == ["self", "metadata"]
    assert tee().TOPIC_PREFIX == "/openral/perception"


def test_the_constructors_take_the_specification_keywords_and_defaults():
    motion = tee().MotionDetector()
    assert (motion.kind, motion.threshold, motion.downsample) == ("motion", 0.02, 1)
    motion = tee().MotionDetector(threshold=0.05, downsample=2)
    assert (motion.threshold, motion.downsample) == (0.05, 2)
    scene = tee().SceneChangeDetector()
    assert (scene.kind, scene.threshold) == ("scene_change", 0.5)
    assert tee().SceneChangeDetector(threshold=0.8).threshold == 0.8
    with pytest.raises(TypeError):
        tee().MotionDetector(0.05)  # keyword-only
    with pytest.raises(TypeError):
        tee().SceneChangeDetector(0.5)


@pytest.mark.parametrize(("threshold", "downsample"), [(-0.1, 1), (1.5, 1), (float("nan"), 1), (0.02, 0), (0.02, 1.5)])
def test_a_motion_detector_refuses_a_threshold_or_step_out_of_range(threshold, downsample):
    with pytest.raises(ROSConfigError):
        tee().MotionDetector(threshold=threshold, downsample=downsample)


@pytest.mark.parametrize("threshold", [0, -1.0, float("nan")])
def test_a_scene_change_detector_refuses_a_threshold_out_of_range(threshold):
    with pytest.raises(ROSConfigError):
        tee().SceneChangeDetector(threshold=threshold)


@pytest.mark.parametrize("form", FORMS)
def test_motion_fires_on_a_changed_frame_and_not_on_the_same_one(form):
    to = FORMS[form]
    motion = tee().MotionDetector()
    assert motion.detect(to(bgr(100)), W, H, "cam") is None  # the first frame: nothing to compare with
    assert motion.detect(to(bgr(100)), W, H, "cam") is None
    moved = bgr(100)
    moved[4:12, 8:24] = 250  # 1/6 of the view changes by 150: a mean change of 25 levels
    found = motion.detect(to(moved), W, H, "cam")
    assert found is not None
    assert found.kind == "motion"
    assert (found.box.x0, found.box.y0, found.box.x1, found.box.y1) == (8, 4, 24, 12)
    summary = motion.summarise(found)
    assert isinstance(summary, str)
    assert summary
    assert "\n" not in summary
    assert motion.detect(to(moved.copy()), W, H, "cam") is None  # still again


def test_detect_takes_the_specification_keywords():
    motion = tee().MotionDetector()
    assert motion.detect(frame_bgr=bgr(0).tobytes(), width=W, height=H, sensor_id="cam") is None
    assert motion.detect(frame_bgr=bgr(255).tobytes(), width=W, height=H, sensor_id="cam") is not None


@pytest.mark.parametrize(("threshold", "fires"), [(0.02, True), (0.035, True), (0.045, False), (0.1, False)])
def test_the_motion_threshold_is_the_mean_absolute_grey_change_over_255(threshold, fires):
    motion = tee().MotionDetector(threshold=threshold)
    motion.detect(bgr(100).tobytes(), W, H, "cam")
    found = motion.detect(bgr(110).tobytes(), W, H, "cam")  # every pixel 10 levels: 10/255 = 0.039
    assert (found is not None) is fires


def test_motion_weighs_the_channels_as_bt601_luma():
    motion = tee().MotionDetector()
    motion.detect(bgr(100).tobytes(), W, H, "cam")
    # Blue 40 levels up is 40 * 0.114 = 4.6 grey levels (0.018, under 0.02); green's is 40 * 0.587 = 23.
    assert motion.detect(bgr((140, 100, 100)).tobytes(), W, H, "cam") is None
    assert motion.detect(bgr((140, 140, 100)).tobytes(), W, H, "cam") is not None


def test_motion_downsample_compares_every_nth_pixel_on_both_axes():
    base = bgr(100)
    odd = base.copy()
    odd[1::2, 1::2] = 255  # only odd rows and odd columns change
    full, sparse = tee().MotionDetector(), tee().MotionDetector(downsample=2)
    for detector in (full, sparse):
        detector.detect(base.tobytes(), W, H, "cam")
    assert full.detect(odd.tobytes(), W, H, "cam") is not None
    assert sparse.detect(odd.tobytes(), W, H, "cam") is None  # never looked at
    even = base.copy()
    even[8:16, 10:20] = 255
    found = sparse.detect(even.tobytes(), W, H, "cam")
    assert found is not None  # in the frame's own coordinates, not the decimated grid's
    assert (found.box.x0, found.box.y0, found.box.x1, found.box.y1) == (10, 8, 20, 16)


def test_motion_compares_each_camera_with_its_own_previous_frame():
    motion = tee().MotionDetector()
    assert motion.detect(bgr(0).tobytes(), W, H, "left") is None
    assert motion.detect(bgr(255).tobytes(), W, H, "right") is None  # right's first frame
    assert motion.detect(bgr(0).tobytes(), W, H, "left") is None


def test_a_gstreamer_buffer_with_padded_rows_is_read_as_the_same_frame():
    width = 5  # 15 bytes a row, padded to 16
    packed, changed = bgr(50, width=width), bgr(50, width=width)
    changed[:, 2:4] = 200
    pad = np.zeros((H, 1), dtype=np.uint8)
    motion = tee().MotionDetector()
    motion.detect(np.hstack([packed.reshape(H, -1), pad]).tobytes(), width, H, "cam")
    found = motion.detect(np.hstack([changed.reshape(H, -1), pad]).tobytes(), width, H, "cam")
    assert found is not None
    assert (found.box.x0, found.box.x1) == (2, 4)


@pytest.mark.parametrize(
    "frame",
    [
        bytes(W * H * 3 - 1),
        bytes(W * H * 3 + 7),
        np.zeros((H, W + 1, 3), dtype=np.uint8),
        np.zeros((H, W, 3), dtype=np.float32),
        np.zeros((H, W, 4), dtype=np.uint8),
    ],
    ids=["short", "long", "wrong shape", "not bytes", "four channels"],
)
@pytest.mark.parametrize("kind", ["MotionDetector", "SceneChangeDetector"])
def test_a_buffer_of_the_wrong_size_is_a_clear_error(kind, frame):
    detector = getattr(tee(), kind)()
    with pytest.raises(ValueError, match=f"{W}x{H}|uint8"):
        detector.detect(frame, W, H, "cam")


@pytest.mark.parametrize("form", FORMS)
def test_a_scene_change_fires_on_a_cut_and_not_on_lighting_drift(form):
    to = FORMS[form]
    scene = tee().SceneChangeDetector()
    assert scene.detect(to(bgr(100)), W, H, "cam") is None  # the first frame
    assert scene.detect(to(bgr(102)), W, H, "cam") is None  # the same histogram bin
    found = scene.detect(to(bgr(230)), W, H, "cam")  # a cut: another scene
    assert found is not None
    assert found.kind == "scene_change"
    summary = scene.summarise(found)
    assert isinstance(summary, str)
    assert summary
    assert "\n" not in summary


@pytest.mark.parametrize(("threshold", "fires"), [(0.5, True), (1.2, True), (1.45, False)])
def test_the_scene_change_threshold_is_a_chisqr_alt_distance(threshold, fires):
    # All black, then half black half white: p = (1, 0), q = (1/2, 1/2) over the end bins, so
    # chisqr_alt = 2 * ((1/2)^2 / (3/2) + (1/2)^2 / (1/2)) = 4/3.
    half = bgr(0)
    half[H // 2 :] = 255
    scene = tee().SceneChangeDetector(threshold=threshold)
    scene.detect(bgr(0).tobytes(), W, H, "cam")
    assert (scene.detect(half.tobytes(), W, H, "cam") is not None) is fires


def test_the_specification_detectors_run_in_the_publisher_at_its_path():
    publisher = tee().PerceptionEventPublisher([tee().MotionDetector(), tee().SceneChangeDetector()], rate_hz=1e6)

    def frame(level: int, stamp_ns: int) -> SensorFrame:
        return SensorFrame(sensor_id="cam", stamp_ns=stamp_ns, width=W, height=H, encoding="bgr8", data=bgr(level))

    assert publisher.process(frame(0, 1)) == []
    events = publisher.process(frame(255, 2))
    assert sorted(event.kind for event in events) == ["motion", "scene_change"]
    assert publisher.errors == 0


# The object detector as the specification describes it, through its path, on the committed cube detector.

CUBE_MODEL = str(Path(__file__).resolve().parents[2] / "models" / "cube_detector.onnx")
CUBE_W, CUBE_H = 480, 240
CUBE = PixelBox(x0=300, y0=100, x1=340, y1=150)


def objects_detector():
    pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")
    return importlib.import_module("openral_runner.backends.gstreamer.objects_detector")


def cube_scene(cube: bool = True) -> np.ndarray:
    """A dark blue floor (BGR), with the magenta cube the committed detector was made for."""
    frame = bgr((90, 60, 40), CUBE_H, CUBE_W)
    if cube:
        frame[int(CUBE.y0) : int(CUBE.y1), int(CUBE.x0) : int(CUBE.x1)] = (200, 90, 210)
    return frame


def test_the_objects_detector_takes_the_specification_keywords_and_defaults():
    cls = objects_detector().ObjectsDetector
    parameters = inspect.signature(cls).parameters
    assert list(parameters)[:6] == ["onnx_path", "labels", "model_id", "input_size", "score_threshold", "device"]
    assert parameters["onnx_path"].kind is inspect.Parameter.POSITIONAL_OR_KEYWORD
    assert all(parameters[name].kind is inspect.Parameter.KEYWORD_ONLY for name in list(parameters)[1:])
    defaults = {name: parameters[name].default for name in ("input_size", "score_threshold", "device")}
    assert defaults == {"input_size": (640, 640), "score_threshold": 0.5, "device": "cpu"}
    detector = cls(CUBE_MODEL, labels=["cube"], model_id="cube")
    assert (detector.kind, detector.labels, detector.model_id) == ("objects", ["cube"], "cube")
    assert (detector.score_threshold, detector.device) == (0.5, "cpu")
    assert cls(CUBE_MODEL, labels=["cube"], model_id="cube", score_threshold=0.8, device="cpu").score_threshold == 0.8
    with pytest.raises(TypeError):
        cls(CUBE_MODEL, ["cube"], "cube")  # keyword-only


@pytest.mark.parametrize(("keyword", "value"), [("device", "cuda"), ("score_threshold", 1.5), ("labels", [])])
def test_the_objects_detector_refuses_a_bad_argument_naming_it(keyword, value):
    arguments = {"labels": ["cube"], "model_id": "cube", keyword: value}
    with pytest.raises(ROSConfigError) as refused:
        objects_detector().ObjectsDetector(CUBE_MODEL, **arguments)
    assert refused.value.field == keyword


@pytest.mark.parametrize("form", FORMS)
def test_the_objects_detector_finds_the_cube_in_an_appsink_buffer(form):
    to = FORMS[form]
    detector = objects_detector().ObjectsDetector(CUBE_MODEL, labels=["cube"], model_id="cube")
    found = detector.detect(to(cube_scene()), CUBE_W, CUBE_H, "front")
    assert isinstance(found, ObjectsMetadata)
    assert (found.kind, found.model_id) == ("objects", "cube")
    assert [d.label for d in found.detections] == ["cube"]
    assert found.detections[0].confidence >= 0.5
    assert found.detections[0].box.iou(CUBE) > 0.8  # in the buffer's own pixels
    assert detector.summarise(found) == "1x cube"
    assert detector.detect(to(cube_scene(cube=False)), CUBE_W, CUBE_H, "front") is None


def test_the_objects_detector_takes_the_detect_keywords():
    detector = objects_detector().ObjectsDetector(CUBE_MODEL, labels=["cube"], model_id="cube")
    found = detector.detect(frame_bgr=cube_scene().tobytes(), width=CUBE_W, height=CUBE_H, sensor_id="front")
    assert found is not None
    assert found.detections[0].label == "cube"


def test_the_objects_summary_counts_each_label():
    detector = objects_detector().ObjectsDetector(CUBE_MODEL, labels=["cube", "cup"], model_id="m")
    box = PixelBox(x0=0, y0=0, x1=4, y1=4)
    found = ObjectsMetadata(
        model_id="m",
        detections=[{"label": label, "confidence": 0.9, "box": box} for label in ("cube", "cup", "cube")],
    )
    assert detector.summarise(found) == "2x cube, 1x cup"


@pytest.mark.parametrize(
    "frame",
    [
        bytes(CUBE_W * CUBE_H * 3 - 1),
        bytes(CUBE_W * CUBE_H * 3 + 7),
        np.zeros((CUBE_H, CUBE_W + 1, 3), dtype=np.uint8),
        np.zeros((CUBE_H, CUBE_W, 3), dtype=np.float32),
    ],
    ids=["short", "long", "wrong shape", "not bytes"],
)
def test_an_objects_buffer_of_the_wrong_size_is_a_clear_error(frame):
    detector = objects_detector().ObjectsDetector(CUBE_MODEL, labels=["cube"], model_id="cube")
    with pytest.raises(ValueError, match=f"{CUBE_W}x{CUBE_H}|uint8"):
        detector.detect(frame, CUBE_W, CUBE_H, "front")
