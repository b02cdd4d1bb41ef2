"""OpenCVThreadSensorReader against real video files made by ``deployments/make_demo_video.py``.

Every frame of those videos carries its index in a strip of black and white blocks, so order,
looping and pacing are checked from the pixels themselves.
"""

from __future__ import annotations

import importlib.util
import itertools
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from structlog.testing import capture_logs

cv2 = pytest.importorskip("cv2", reason="needs the 'opencv' extra: uv sync --extra opencv")

from openral_core import (  # noqa: E402
    FrameEncoding,
    RobotEnvironment,
    ROSConfigError,
    ROSHardwareError,
    ROSPerceptionStale,
    ROSRuntimeError,
    SensorFrame,
    SensorReaderConfig,
)
from openral_runner.backends.opencv_thread import OpenCVThreadParams, OpenCVThreadSensorReader  # noqa: E402
from openral_runner.sensor_reader import SensorReader  # noqa: E402

REPO = Path(__file__).resolve().parents[3]
MS = 1_000_000
ANY_AGE_MS = 10_000
"""An age limit for reads that check something other than staleness (holds on a loaded machine)."""


def _load_video_tools() -> ModuleType:
    spec = importlib.util.spec_from_file_location("make_demo_video", REPO / "deployments" / "make_demo_video.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


video_tools = _load_video_tools()


@pytest.fixture(scope="module")
def videos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("videos")
    return {
        "short": video_tools.write_demo_video(root / "short.mp4", width=160, height=120, frames=10),
        "medium": video_tools.write_demo_video(root / "medium.mp4", width=160, height=120, frames=90),
    }


def reference_frames(path: Path) -> list[np.ndarray]:
    """Every frame of ``path``, decoded directly with OpenCV (BGR)."""
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    return frames


def reader(path: Path, **kwargs: Any) -> OpenCVThreadSensorReader:
    return OpenCVThreadSensorReader(sensor_id="front", device=path, **kwargs)


def collect(cam: SensorReader, seconds: float) -> list[SensorFrame]:
    """Every frame ``read_synced`` hands out for ``seconds``."""
    frames = [cam.read_latest(max_age_ms=ANY_AGE_MS)]
    end = time.monotonic_ns() + round(seconds * 1e9)
    while time.monotonic_ns() < end:
        frames.append(cam.read_synced(time.monotonic_ns() + 2000 * MS, newer_than_ns=frames[-1].stamp_ns))
    return frames


def capture_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("openral-opencv-")]


def test_is_a_sensor_reader(videos: dict[str, Path]) -> None:
    assert isinstance(reader(videos["short"]), SensorReader)


def test_frames_have_declared_size_exact_pixels_and_order(videos: dict[str, Path]) -> None:
    expected = reference_frames(videos["medium"])
    with reader(videos["medium"], fps=60, width=160, height=120) as cam:
        frames = collect(cam, 0.5)
    indices = [video_tools.read_frame_index(f.as_array()) for f in frames]
    assert len(frames) >= 10
    assert indices == sorted(set(indices)), "frames out of order or repeated"
    assert [f.seq for f in frames] == sorted({f.seq for f in frames})
    for frame, index in zip(frames, indices, strict=True):
        assert (frame.width, frame.height, frame.encoding) == (160, 120, FrameEncoding.BGR8)
        assert frame.sensor_id == "front"
        assert np.array_equal(frame.as_array(), expected[index])


def test_paced_file_delivers_the_requested_rate(videos: dict[str, Path]) -> None:
    with reader(videos["medium"], fps=30) as cam:
        start_ns = time.monotonic_ns()
        frames = collect(cam, 1.3)
        report = cam.report()
        elapsed_s = (time.monotonic_ns() - start_ns) / 1e9
    span_s = (frames[-1].stamp_ns - frames[0].stamp_ns) / 1e9
    rate = (frames[-1].seq - frames[0].seq) / span_s
    assert rate == pytest.approx(30, rel=0.3)
    assert report["measured_fps"] == pytest.approx(30, rel=0.3)
    assert report["delivered_fps"] == pytest.approx(30, rel=0.3)
    assert report["frames"] == pytest.approx(30 * elapsed_s, rel=0.3)
    assert report["file_fps"] == pytest.approx(30)
    # content follows wall time too: the file plays at 30 frames of video per second
    shown = video_tools.read_frame_index(frames[-1].as_array()) - video_tools.read_frame_index(frames[0].as_array())
    assert shown / span_s == pytest.approx(30, rel=0.3)


def test_paced_at_a_rate_other_than_the_files(videos: dict[str, Path]) -> None:
    with reader(videos["medium"], fps=60) as cam:
        frames = collect(cam, 0.6)
    rate = (frames[-1].seq - frames[0].seq) / ((frames[-1].stamp_ns - frames[0].stamp_ns) / 1e9)
    assert rate == pytest.approx(60, rel=0.3)


def test_a_stall_skips_slots_instead_of_bursting(videos: dict[str, Path]) -> None:
    period_ns = round(1e9 / 50)
    stamps: list[int] = []

    class StallingReader(OpenCVThreadSensorReader):
        def _capture(self, cap: Any) -> tuple[int, np.ndarray] | None:
            if len(stamps) == 5:
                time.sleep(3.5 * period_ns / 1e9)
            captured = super()._capture(cap)
            if captured is not None:
                stamps.append(captured[0])
            return captured

    with StallingReader(sensor_id="front", device=videos["medium"], fps=50) as cam:
        deadline = time.monotonic() + 10
        while len(stamps) < 7 or stamps[-1] <= stamps[5] + 10 * period_ns:  # ten slots past the stall
            assert time.monotonic() < deadline, f"only {len(stamps)} frames captured"
            time.sleep(0.005)
        report = cam.report()
    after_stall = [s for s in stamps[6:] if s <= stamps[5] + 10 * period_ns]
    assert report["dropped"] >= 2
    assert len(after_stall) <= 11, "missed slots were caught up in a burst"


def test_looping_file_starts_again(videos: dict[str, Path]) -> None:
    with reader(videos["short"], fps=60, loop=True) as cam:
        frames = collect(cam, 0.5)
        report = cam.report()
    indices = [video_tools.read_frame_index(f.as_array()) for f in frames]
    assert report["loops"] >= 1
    assert not report["end_of_stream"]
    assert any(b < a for a, b in itertools.pairwise(indices)), f"never wrapped: {indices}"
    assert set(indices) <= set(range(10))


def test_end_of_file_serves_last_frame_until_stale(videos: dict[str, Path]) -> None:
    with reader(videos["short"], fps=60, default_max_age_ms=100) as cam:
        deadline = time.monotonic() + 5
        while not cam.report()["end_of_stream"]:
            assert time.monotonic() < deadline, "end of stream never reached"
            time.sleep(0.005)
        last = cam.read_latest(max_age_ms=ANY_AGE_MS)
        assert video_tools.read_frame_index(last.as_array()) == 9
        while capture_threads():
            assert time.monotonic() < deadline, "the capture thread should end at the end of the file"
            time.sleep(0.005)
        assert cam.is_open
        time.sleep(max(0.0, 0.11 - last.age_ms(time.monotonic_ns()) / 1e3))
        with pytest.raises(ROSPerceptionStale, match="ms old"):
            cam.read_latest()
        with pytest.raises(ROSPerceptionStale):
            cam.read_synced(time.monotonic_ns() + 30 * MS, newer_than_ns=last.stamp_ns)


def test_read_synced_waits_for_a_newer_frame_then_times_out(videos: dict[str, Path]) -> None:
    with reader(videos["short"], fps=30, default_max_age_ms=1000) as cam:
        first = cam.read_latest(max_age_ms=ANY_AGE_MS)
        newer = cam.read_synced(time.monotonic_ns() + 500 * MS, newer_than_ns=first.stamp_ns)
        assert newer.stamp_ns > first.stamp_ns
        assert newer.seq > first.seq
        future = time.monotonic_ns() + 10_000 * MS  # no frame can be newer than this
        start = time.monotonic_ns()
        with pytest.raises(ROSPerceptionStale):
            cam.read_synced(start + 50 * MS, newer_than_ns=future)
        waited_ms = (time.monotonic_ns() - start) / MS
        assert 45 <= waited_ms < 1000


@pytest.mark.parametrize("encoding", [FrameEncoding.RGB8, FrameEncoding.MONO8])
def test_colour_conversion(videos: dict[str, Path], encoding: FrameEncoding) -> None:
    expected = reference_frames(videos["medium"])
    with reader(videos["medium"], fps=60, encoding=encoding) as cam:
        frames = collect(cam, 0.2)
    for frame in frames:
        pixels = frame.as_array()
        reference = expected[video_tools.read_frame_index(pixels)]
        assert frame.encoding is encoding
        if encoding is FrameEncoding.RGB8:
            assert pixels.shape == (120, 160, 3)
            assert np.array_equal(pixels, reference[:, :, ::-1])
            rows, cols = video_tools.patch_boxes(160, 120)["blue"]
            assert pixels[rows, cols].reshape(-1, 3).mean(axis=0) == pytest.approx((0, 0, 255), abs=12)
        else:
            assert pixels.shape == (120, 160)
            assert np.array_equal(pixels, cv2.cvtColor(reference, cv2.COLOR_BGR2GRAY))


def test_frames_are_the_capture_arrays_and_never_overwritten(videos: dict[str, Path]) -> None:
    with reader(videos["medium"], fps=60) as cam:
        first = cam.read_latest(max_age_ms=ANY_AGE_MS)
        kept = first.as_array().copy()
        later = collect(cam, 0.2)
    assert isinstance(first.data, np.ndarray)
    assert first.as_array() is first.data
    assert np.shares_memory(first.as_array(), first.data)
    assert len(later) > 3
    assert np.array_equal(first.as_array(), kept), "a served frame changed after later captures"
    assert not any(np.shares_memory(first.data, f.data) for f in later[1:])


def test_requested_size_not_delivered_is_a_config_error(videos: dict[str, Path]) -> None:
    cam = reader(videos["short"], width=320, height=240)
    with pytest.raises(ROSConfigError, match=r"requested 320x240 .* 160x120") as info:
        cam.open()
    assert "width: 160" in str(info.value)
    assert not cam.is_open
    assert capture_threads() == []


def test_missing_or_unreadable_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match="not found"):
        reader(tmp_path / "nope.mp4").open()
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video" * 100)
    with pytest.raises(ROSConfigError, match="cannot decode"):
        reader(junk).open()


def test_unopenable_camera_is_a_hardware_error() -> None:
    cam = OpenCVThreadSensorReader(sensor_id="wrist", device=97)
    with pytest.raises(ROSHardwareError, match="97"):
        cam.open()


def test_closed_reader_raises_runtime_error(videos: dict[str, Path]) -> None:
    cam = reader(videos["short"])
    with pytest.raises(ROSRuntimeError, match="closed"):
        cam.read_latest()
    with cam:
        cam.read_latest(max_age_ms=ANY_AGE_MS)
    for read in (cam.read_latest, lambda: cam.read_synced(time.monotonic_ns() + 10 * MS)):
        with pytest.raises(ROSRuntimeError, match="closed") as info:
            read()
        assert not isinstance(info.value, ROSPerceptionStale)


def test_close_joins_the_thread_is_idempotent_and_reopens(videos: dict[str, Path]) -> None:
    cam = reader(videos["medium"], loop=True)
    cam.open()
    cam.open()  # idempotent
    assert [t.name for t in capture_threads()] == ["openral-opencv-front"]
    cam.close()
    assert capture_threads() == []
    cam.close()
    with cam:
        assert cam.read_latest(max_age_ms=ANY_AGE_MS).seq < 60  # counting restarted
        assert len(capture_threads()) == 1
    assert capture_threads() == []


def test_from_config_passes_sensor_fields_and_resolves_relative_paths(videos: dict[str, Path]) -> None:
    config = SensorReaderConfig(
        sensor_id="front",
        fps=25,
        width=160,
        height=120,
        encoding=FrameEncoding.RGB8,
        max_age_ms=70,
        backend_params={"device": videos["short"].name, "loop": True, "api_preference": "ffmpeg"},
    )
    cam = OpenCVThreadSensorReader.from_config(config, hal=None, robot=None, base_dir=videos["short"].parent)
    assert cam.device == str(videos["short"])
    assert (cam.config.fps, cam.config.width, cam.config.height) == (25, 160, 120)
    assert cam.config.encoding is FrameEncoding.RGB8
    assert cam.config.max_age_ms == 70
    assert cam.params.loop
    assert cam.params.api_preference == "ffmpeg"
    assert cam.paced
    with cam:
        assert cam.read_latest(max_age_ms=ANY_AGE_MS).encoding is FrameEncoding.RGB8


def test_from_config_wrong_key_names_field_and_allowed_keys() -> None:
    config = SensorReaderConfig(sensor_id="front", backend_params={"device": "a.mp4", "lopo": True})
    with pytest.raises(ROSConfigError) as info:
        OpenCVThreadSensorReader.from_config(config, hal=None, robot=None)
    text = str(info.value)
    assert "lopo" in text
    assert "allowed keys" in text
    assert "loop" in text
    assert "sensors[front].backend_params" in text
    assert "did you mean 'loop'" in text
    with pytest.raises(ROSConfigError, match="device"):
        OpenCVThreadSensorReader.from_config(SensorReaderConfig(sensor_id="front"), hal=None, robot=None)


def test_invalid_arguments_are_config_errors(videos: dict[str, Path]) -> None:
    with pytest.raises(ROSConfigError, match="video files only"):
        OpenCVThreadSensorReader(sensor_id="cam", device=0, loop=True)
    with pytest.raises(ROSConfigError, match="video files only"):
        OpenCVThreadSensorReader(sensor_id="cam", device="rtsp://cam.local/stream", paced=True)
    with pytest.raises(ROSConfigError, match="bgr8, rgb8 or mono8"):
        reader(videos["short"], encoding=FrameEncoding.MONO16)
    assert OpenCVThreadSensorReader(sensor_id="cam", device="2").device == 2
    assert not OpenCVThreadSensorReader(sensor_id="cam", device="/dev/video0").is_file


def test_the_keyword_form_is_checked_by_the_models_a_deployment_is(videos: dict[str, Path]) -> None:
    with pytest.raises(ROSConfigError, match="fps"):
        OpenCVThreadSensorReader(sensor_id="cam", device=0, fps=0)
    with pytest.raises(ROSConfigError, match="allowed keys") as info:
        reader(videos["short"], lopo=True)
    assert "did you mean 'loop'" in str(info.value)
    cam = reader(videos["short"], fps=12, default_max_age_ms=40, loop=True)
    assert (cam.config.sensor_id, cam.config.fps, cam.config.max_age_ms) == ("front", 12, 40)
    assert cam.params == OpenCVThreadParams(device=str(videos["short"]), loop=True)


class FakeLiveCapture:
    """A 'live camera' serving a video file's frames: optionally slow, optionally dying."""

    def __init__(self, path: Path, *, frames_ok: int = 1_000_000, frame_interval_s: float = 0.0) -> None:
        self._cap = cv2.VideoCapture(str(path))
        self.frames_ok = frames_ok
        self.frame_interval_s = frame_interval_s
        self.grabs = 0
        self.props: dict[int, float] = {}

    def isOpened(self) -> bool:
        return bool(self._cap.isOpened())

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return self.props.get(prop, 0.0)

    def grab(self) -> bool:
        self.grabs += 1
        time.sleep(self.frame_interval_s)
        return self.grabs <= self.frames_ok and bool(self._cap.grab())

    def retrieve(self) -> tuple[bool, np.ndarray]:
        return self._cap.retrieve()

    def release(self) -> None:
        self._cap.release()


class LiveReader(OpenCVThreadSensorReader):
    def __init__(self, capture: FakeLiveCapture, **kwargs: Any) -> None:
        super().__init__(sensor_id="wrist", device=0, **kwargs)
        self.capture = capture

    def _open_capture(self) -> Any:
        return self.capture


def test_live_camera_applies_requested_settings(videos: dict[str, Path]) -> None:
    capture = FakeLiveCapture(videos["medium"])
    with LiveReader(capture, fps=15, width=160, height=120, fourcc="MJPG", buffer_size=1):
        pass
    assert capture.props[cv2.CAP_PROP_FPS] == 15
    assert capture.props[cv2.CAP_PROP_FRAME_WIDTH] == 160
    assert capture.props[cv2.CAP_PROP_FRAME_HEIGHT] == 120
    assert capture.props[cv2.CAP_PROP_BUFFERSIZE] == 1
    assert capture.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter.fourcc(*"MJPG")


def test_camera_that_stops_delivering_latches_an_error(videos: dict[str, Path]) -> None:
    capture = FakeLiveCapture(videos["medium"], frames_ok=3, frame_interval_s=0.005)
    with LiveReader(capture, fps=200, max_read_failures=4) as cam:
        deadline = time.monotonic() + 5
        while cam.report()["read_failures"] < 4:
            assert time.monotonic() < deadline
            time.sleep(0.005)
        with pytest.raises(ROSRuntimeError, match="no frame in 4 reads in a row") as info:
            cam.read_latest(max_age_ms=ANY_AGE_MS)
        assert not isinstance(info.value, ROSPerceptionStale)
        with pytest.raises(ROSRuntimeError, match="no frame in 4 reads"):
            cam.read_synced(time.monotonic_ns() + 10 * MS, newer_than_ns=time.monotonic_ns())
        assert capture.grabs == 3 + 4


def test_slow_camera_is_measured_and_warned_about(videos: dict[str, Path]) -> None:
    capture = FakeLiveCapture(videos["medium"], frame_interval_s=0.1)
    with capture_logs() as logs, LiveReader(capture, fps=30) as cam:
        deadline = time.monotonic() + 5
        while cam.report()["measured_fps"] is None:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        report = cam.report()
    warnings = [e for e in logs if e["event"] == "camera delivers fewer frames than requested"]
    assert len(warnings) == 1
    assert warnings[0]["requested_fps"] == 30
    assert 3 < report["measured_fps"] < 0.9 * 30  # about 10; lower on a loaded machine
    assert report["dropped"] >= 10  # every 100 ms gap is two missed 30 fps frames


def test_missing_opencv_names_the_extra() -> None:
    code = (
        "import sys\n"
        "sys.modules['cv2'] = None\n"
        "from openral_core import ROSDependencyMissing\n"
        "try:\n"
        "    import openral_runner.backends.opencv_thread\n"
        "except ROSDependencyMissing as exc:\n"
        "    print(exc)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert "cv2" in proc.stdout
    assert "--extra opencv" in proc.stdout


def test_video_file_deployment_opens_its_camera() -> None:
    path = REPO / "deployments" / "video_file.yaml"
    env = RobotEnvironment.from_yaml(path)
    (config,) = env.sensors
    with OpenCVThreadSensorReader.from_config(config, hal=None, robot=None, base_dir=path.parent) as cam:
        frame = cam.read_latest(max_age_ms=ANY_AGE_MS)
        assert (frame.width, frame.height) == (config.width, config.height)
        assert cam.paced
        assert cam.params.loop
