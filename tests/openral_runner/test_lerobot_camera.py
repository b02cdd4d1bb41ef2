"""The ``lerobot_camera`` sensor backend runs LeRobot's own camera code on openral's capture thread.

Real sources, no stand-ins for LeRobot: its ``ZMQCamera`` subscribes to a ZeroMQ publisher in the
test that speaks LeRobot's JSON protocol (frames encoded by LeRobot's own ``encode_image``), and
its ``OpenCVCamera`` reads a video file written here. Needs the ``lerobot`` extra (Python 3.12).
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

pytest.importorskip("torch", reason=LEROBOT_REASON)
pytest.importorskip("lerobot", reason=LEROBOT_REASON)

import cv2  # noqa: E402
import zmq  # noqa: E402
from click.testing import CliRunner  # noqa: E402
from lerobot.cameras.zmq.image_server import encode_image  # noqa: E402

from openral_cli.main import cli  # noqa: E402
from openral_core import (  # noqa: E402
    FrameEncoding,
    RobotEnvironment,
    ROSConfigError,
    ROSHardwareError,
    ROSPerceptionStale,
    ROSRuntimeError,
    SensorFrame,
    SensorReaderConfig,
    WorldState,
)
from openral_runner.backends.lerobot_camera import LeRobotCameraSensorReader  # noqa: E402
from openral_runner.factory import SENSOR_BACKEND_REGISTRY, build_runner  # noqa: E402

DEPLOYMENTS = Path(__file__).resolve().parents[2] / "deployments"

WIDTH, HEIGHT = 160, 120
RED, BLUE = (255, 0, 0), (0, 0, 255)
"""The published picture (RGB, LeRobot's order): red on the top left, blue on the top right."""

CODES = 25
"""Frame k's bottom half is grey ``10 * (k % CODES)``: which frame arrived, read back through JPEG."""


class Publisher:
    """A ZeroMQ PUB socket sending LeRobot's JSON frames (base64 JPEG from LeRobot's encoder) at a steady rate."""

    def __init__(self, *, camera_name: str = "cam", rate_hz: float = 30.0) -> None:
        self.camera_name = camera_name
        self.period_s = 1.0 / rate_hz
        self.context = zmq.Context()
        self.socket = self.context.socket(zmq.PUB)
        self.socket.setsockopt(zmq.LINGER, 0)
        self.port = self.socket.bind_to_random_port("tcp://127.0.0.1")
        self.sent_ns: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="test-zmq-publisher", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        index = 0
        while not self._stop.wait(self.period_s):
            image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
            image[: HEIGHT // 2, : WIDTH // 2] = RED
            image[: HEIGHT // 2, WIDTH // 2 :] = BLUE
            image[HEIGHT // 2 :] = 10 * (index % CODES)
            message = {"timestamps": {self.camera_name: time.time()}, "images": {self.camera_name: encode_image(image)}}
            self.sent_ns.append(time.monotonic_ns())
            self.socket.send_string(json.dumps(message))
            index += 1

    def stop(self) -> None:
        """Stop sending (the socket stays bound: a silent publisher, not a vanished one)."""
        self._stop.set()
        self._thread.join(5)

    def close(self) -> None:
        self.stop()
        self.socket.close()
        self.context.term()


@pytest.fixture
def publisher() -> Iterator[Publisher]:
    pub = Publisher()
    yield pub
    pub.close()


def zmq_sensor(port: int, *, encoding: str = "bgr8", **params: Any) -> SensorReaderConfig:
    backend_params = {
        "type": "zmq",
        "server_address": "127.0.0.1",
        "port": port,
        "camera_name": "cam",
        "warmup_s": 0,
        "timeout_ms": 1000,
        **params,
    }
    return SensorReaderConfig.model_validate(
        {
            "sensor_id": "cam",
            "backend": "lerobot_camera",
            "width": WIDTH,
            "height": HEIGHT,
            "encoding": encoding,
            "max_age_ms": 200,
            "backend_params": backend_params,
        }
    )


def build(config: SensorReaderConfig, base_dir: Path | None = None) -> LeRobotCameraSensorReader:
    reader = SENSOR_BACKEND_REGISTRY.resolve("lerobot_camera", field="backend").from_config(
        config, hal=None, robot=None, base_dir=base_dir
    )
    assert isinstance(reader, LeRobotCameraSensorReader)
    return reader


def next_frame(reader: LeRobotCameraSensorReader, after: SensorFrame | None) -> SensorFrame:
    return reader.read_synced(time.monotonic_ns() + 5_000_000_000, newer_than_ns=0 if after is None else after.stamp_ns)


def lerobot_threads() -> list[str]:
    return [
        t.name for t in threading.enumerate() if t.name.endswith("_read_loop") or t.name.startswith("openral-lerobot")
    ]


@pytest.mark.parametrize(
    ("encoding", "top_left", "top_right"),
    [("bgr8", RED[::-1], BLUE[::-1]), ("rgb8", RED, BLUE), ("mono8", None, None)],
)
def test_zmq_frames_arrive_in_the_slot_in_the_sensor_encoding_stamped_at_capture(
    publisher: Publisher, encoding: str, top_left: tuple[int, ...] | None, top_right: tuple[int, ...] | None
) -> None:
    reader = build(zmq_sensor(publisher.port, encoding=encoding))
    reader.open()
    try:
        frames: list[tuple[SensorFrame, int]] = []
        frame = None
        for _ in range(15):
            frame = next_frame(reader, frame)
            frames.append((frame, time.monotonic_ns()))
    finally:
        reader.close()

    for frame, read_ns in frames:
        pixels = frame.as_array()
        assert frame.encoding == FrameEncoding(encoding)
        if top_left is None:
            assert pixels.shape == (HEIGHT, WIDTH)
            # Luma of pure red and pure blue: they stay apart in grey.
            assert abs(int(pixels[HEIGHT // 4, WIDTH // 4]) - 76) <= 6
            assert abs(int(pixels[HEIGHT // 4, 3 * WIDTH // 4]) - 29) <= 6
        else:
            assert pixels.shape == (HEIGHT, WIDTH, 3)
            assert np.abs(pixels[HEIGHT // 4, WIDTH // 4].astype(int) - top_left).max() <= 6
            assert np.abs(pixels[HEIGHT // 4, 3 * WIDTH // 4].astype(int) - top_right).max() <= 6
        # The stamp is this very frame's capture: after the publisher sent it, before the test saw it.
        code = round(float(pixels[3 * HEIGHT // 4, WIDTH // 2].mean()) / 10) % CODES
        sent = [ns for index, ns in enumerate(publisher.sent_ns) if index % CODES == code and ns <= read_ns]
        assert sent, code
        assert sent[-1] <= frame.stamp_ns <= read_ns
    stamps = [frame.stamp_ns for frame, _ in frames]
    assert stamps == sorted(stamps)
    assert len(set(stamps)) == len(stamps)
    assert [frame.seq for frame, _ in frames] == sorted({frame.seq for frame, _ in frames})


def test_a_silent_publisher_makes_the_sensor_stale_then_failed_and_it_still_closes(publisher: Publisher) -> None:
    reader = build(zmq_sensor(publisher.port, read_timeout_ms=300, max_read_failures=2))
    reader.open()
    try:
        last = next_frame(reader, None)
        publisher.stop()
        # Within max_age_ms of the last frame the sensor is served; after it, stale.
        stale: ROSPerceptionStale | None = None
        while stale is None:
            try:
                reader.read_latest()
            except ROSPerceptionStale as exc:
                stale = exc
            else:
                time.sleep(0.005)  # polling for the moment it turns stale
        assert stale.age_ms is not None
        assert stale.age_ms > 200
        assert reader._slot.error is None, "stale first: two reads of 300 ms have not failed yet"
        # Two reads of 300 ms without a frame: the failure is latched and raised on every read.
        deadline = time.monotonic() + 10
        while reader._slot.error is None and time.monotonic() < deadline:
            reader._slot.wait_for_frame(newer_than_ns=last.stamp_ns, deadline_ns=time.monotonic_ns() + 50_000_000)
        with pytest.raises(ROSRuntimeError, match="no frame in 2 reads in a row") as failed:
            reader.read_latest(max_age_ms=float("inf"))
        assert not isinstance(failed.value, ROSPerceptionStale)
        assert reader.report()["read_failures"] >= 2
    finally:
        started = time.monotonic()
        reader.close()
    assert time.monotonic() - started < 5
    assert not reader.is_open
    with pytest.raises(ROSRuntimeError, match="closed"):
        reader.read_latest()
    assert lerobot_threads() == []


def test_close_disconnects_lerobot_and_the_reader_opens_again(publisher: Publisher) -> None:
    reader = build(zmq_sensor(publisher.port))
    reader.open()
    first = next_frame(reader, None)
    reader.close()
    assert lerobot_threads() == []
    reader.open()
    try:
        again = next_frame(reader, None)
        assert again.stamp_ns > first.stamp_ns
    finally:
        reader.close()
    assert lerobot_threads() == []


@pytest.mark.parametrize("warmup_s", [0, 1], ids=["no-warm-up", "warm-up"])
def test_opening_without_a_publisher_is_a_hardware_error_naming_the_sensor(warmup_s: int) -> None:
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        port = free.getsockname()[1]
    reader = build(zmq_sensor(port, timeout_ms=200, read_timeout_ms=200, warmup_s=warmup_s))
    with pytest.raises(ROSHardwareError, match="sensor 'cam'"):
        reader.open()
    assert not reader.is_open
    assert lerobot_threads() == []


def test_a_size_other_than_the_sensors_is_refused_at_open(publisher: Publisher) -> None:
    config = zmq_sensor(publisher.port).model_copy(update={"width": 2 * WIDTH, "height": 2 * HEIGHT})
    reader = build(config)
    with pytest.raises(ROSConfigError, match=f"delivers {WIDTH}x{HEIGHT}"):
        reader.open()
    assert lerobot_threads() == []


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")  # LeRobot's reader at the end
def test_lerobot_opencv_camera_reads_a_video_file_to_its_end_then_the_sensor_fails(tmp_path: Path) -> None:
    """LeRobot takes a file path, but reads it as fast as it decodes, once: its reader thread ends at the end
    of the file by raising (hence the warning filter), and openral then reports the sensor failed."""
    rng = np.random.default_rng(0)
    image = np.zeros((480, 640, 3), np.uint8)  # BGR, as OpenCV writes
    image[:240, :320] = RED[::-1]
    image[:240, 320:] = BLUE[::-1]
    image[240:] = rng.integers(0, 256, (240, 640, 3), dtype=np.uint8)  # slows decoding down to a few ms
    writer = cv2.VideoWriter(str(tmp_path / "clip.avi"), cv2.VideoWriter.fourcc(*"MJPG"), 30, (640, 480))
    for _ in range(200):
        writer.write(image)
    writer.release()
    config = SensorReaderConfig.model_validate(
        {
            "sensor_id": "file",
            "backend": "lerobot_camera",
            "encoding": "rgb8",
            "backend_params": {"type": "opencv", "index_or_path": "clip.avi", "warmup_s": 0, "max_read_failures": 3},
        }
    )
    reader = build(config, base_dir=tmp_path)
    assert reader.lerobot_config.index_or_path == tmp_path / "clip.avi"
    reader.open()
    try:
        frame = next_frame(reader, None)
        pixels = frame.as_array()
        assert pixels.shape == (480, 640, 3)
        assert np.abs(pixels[120, 160].astype(int) - RED).max() <= 6
        assert np.abs(pixels[120, 480].astype(int) - BLUE).max() <= 6
        deadline = time.monotonic() + 30
        while reader._slot.error is None and time.monotonic() < deadline:
            reader._slot.wait_for_frame(newer_than_ns=time.monotonic_ns(), deadline_ns=time.monotonic_ns() + 50_000_000)
        with pytest.raises(ROSRuntimeError, match="no frame in 3 reads in a row"):
            reader.read_latest(max_age_ms=float("inf"))
        assert 1 <= reader.frames_published <= 200
    finally:
        reader.close()
    assert lerobot_threads() == []


def test_a_missing_video_file_is_refused_when_the_sensor_is_built(tmp_path: Path) -> None:
    config = SensorReaderConfig.model_validate(
        {
            "sensor_id": "file",
            "backend": "lerobot_camera",
            "backend_params": {"type": "opencv", "index_or_path": "x.mp4"},
        }
    )
    with pytest.raises(ROSConfigError) as refused:
        build(config, base_dir=tmp_path)
    assert refused.value.field == "sensors[file].backend_params.index_or_path"


@pytest.mark.parametrize(
    ("params", "field", "words"),
    [
        ({"type": "zmqq", "server_address": "x"}, "sensors[cam].backend_params.type", "did you mean 'zmq'"),
        ({"type": "zmq", "server_adress": "x"}, "sensors[cam].backend_params.server_adress", "server_address"),
        ({"type": "zmq", "server_address": "x", "port": 70000}, "sensors[cam].backend_params", "65535"),
        ({"type": "zmq", "server_address": "x", "fps": 30}, "sensors[cam].backend_params.fps", "sensors[cam].fps"),
        ({"server_address": "x"}, "sensors[cam].backend_params.type", "required"),
        (
            {"type": "zmq", "server_address": "x", "max_read_failures": 0},
            "sensors[cam].backend_params.max_read_failures",
            "1",
        ),
    ],
)
def test_a_wrong_key_or_type_names_its_field(params: dict[str, Any], field: str, words: str) -> None:
    config = SensorReaderConfig.model_validate(
        {"sensor_id": "cam", "backend": "lerobot_camera", "backend_params": params}
    )
    with pytest.raises(ROSConfigError) as refused:
        build(config)
    assert refused.value.field == field
    assert words in str(refused.value)


def test_a_depth_encoding_is_refused_on_the_sensors_field() -> None:
    config = SensorReaderConfig.model_validate(
        {
            "sensor_id": "cam",
            "backend": "lerobot_camera",
            "encoding": "mono16",
            "backend_params": {"type": "zmq", "server_address": "x"},
        }
    )
    with pytest.raises(ROSConfigError) as refused:
        build(config)
    assert refused.value.field == "sensors[cam].encoding"


def test_the_sensors_size_and_set_rate_reach_lerobots_config() -> None:
    base = {"sensor_id": "cam", "backend": "lerobot_camera", "width": 64, "height": 48}
    params = {"type": "opencv", "index_or_path": 0}
    unset = build(SensorReaderConfig.model_validate({**base, "backend_params": params}))
    assert (unset.lerobot_config.width, unset.lerobot_config.height, unset.lerobot_config.fps) == (64, 48, None)
    assert unset.lerobot_config.index_or_path == 0
    rate = build(SensorReaderConfig.model_validate({**base, "fps": 15, "backend_params": params}))
    assert rate.lerobot_config.fps == 15
    with pytest.raises(ROSConfigError) as refused:
        build(SensorReaderConfig.model_validate({**base, "fps": 12.5, "backend_params": params}))
    assert refused.value.field == "sensors[cam].fps"


def twin_deployment(port: int, **sensor: Any) -> dict[str, Any]:
    data = yaml.safe_load((DEPLOYMENTS / "video_file.yaml").read_text(encoding="utf-8"))
    data["name"] = "lerobot_camera"
    data["sensors"] = [
        {
            "sensor_id": "front",
            "backend": "lerobot_camera",
            "width": WIDTH,
            "height": HEIGHT,
            "encoding": "rgb8",
            "max_age_ms": 200,
            "backend_params": {
                "type": "zmq",
                "server_address": "127.0.0.1",
                "port": port,
                "camera_name": "cam",
                "warmup_s": 0,
            },
            **sensor,
        }
    ]
    return data


def test_openral_validate_builds_the_sensor_without_connecting_to_the_camera(tmp_path: Path) -> None:
    pytest.importorskip("mujoco", reason="the deployment drives the SO-101 twin: needs the 'twin' extra")
    with socket.socket() as camera_host:  # where the camera would be: any connection to it shows up here
        camera_host.bind(("127.0.0.1", 0))
        camera_host.listen()
        camera_host.settimeout(0.5)
        path = tmp_path / "deployment.yaml"
        path.write_text(yaml.safe_dump(twin_deployment(camera_host.getsockname()[1])), encoding="utf-8")
        result = CliRunner().invoke(cli, ["validate", str(path)])
        assert result.exit_code == 0, result.output
        assert "1 sensor(s)" in result.output
        with pytest.raises(TimeoutError):
            camera_host.accept()

    bad = twin_deployment(1234)
    bad["sensors"][0]["backend_params"]["server_adress"] = bad["sensors"][0]["backend_params"].pop("server_address")
    path.write_text(yaml.safe_dump(bad), encoding="utf-8")
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2
    assert "sensors[front].backend_params.server_adress" in result.output


@pytest.mark.slow
def test_a_twin_deployment_with_a_lerobot_camera_hands_its_frames_to_the_skill(publisher: Publisher) -> None:
    pytest.importorskip("mujoco", reason="the deployment drives the SO-101 twin: needs the 'twin' extra")
    env = RobotEnvironment.model_validate(twin_deployment(publisher.port))
    runner, skill = build_runner(env, base_dir=DEPLOYMENTS)
    seen: list[WorldState] = []
    step = skill.step

    def recording_step(world: WorldState) -> Any:
        seen.append(world)
        return step(world)

    skill.step = recording_step  # type: ignore[method-assign]
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        (reader,) = runner.sensor_readers
        reader.read_synced(time.monotonic_ns() + 5_000_000_000)
        published_before = reader.frames_published
        result = runner.run(60)
        published = reader.frames_published - published_before
    finally:
        runner.deactivate()
        skill.shutdown()

    assert result.n_ticks == 60
    # As in the shipped camera deployments: on a loaded machine a late frame withholds its tick.
    reasons = [t.withheld_reason for t in runner.recent_ticks if t.withheld_reason]
    assert set(reasons) <= {"stale_sensor"}, reasons
    assert len(reasons) <= 6, reasons
    assert len(seen) == 60 - len(reasons)
    seqs = set()
    for world in seen:
        assert world.image_frames is not None
        frame = world.image_frames["front"]
        pixels = frame.as_array()
        assert pixels.shape == (HEIGHT, WIDTH, 3)
        assert frame.encoding == FrameEncoding.RGB8
        assert np.abs(pixels[HEIGHT // 4, WIDTH // 4].astype(int) - RED).max() <= 6
        seqs.add(frame.seq)
    # The camera kept delivering (about 30 fps for two seconds) and the skill saw most of its frames.
    assert published >= 30, published
    assert len(seqs) >= 0.65 * published, (len(seqs), published)
    assert lerobot_threads() == []


# -- a camera from a third-party lerobot_camera_* package ------------------------------------------------

PATTERN_CONFIG = """
from dataclasses import dataclass

from lerobot.cameras.configs import CameraConfig


@CameraConfig.register_subclass("test_pattern")
@dataclass
class TestPatternCameraConfig(CameraConfig):
    level: int = 100
"""
PATTERN_CAMERA = '''
import time

import numpy as np
from lerobot.cameras.camera import Camera

from .config_test_pattern import TestPatternCameraConfig


class TestPatternCamera(Camera):
    """Frames of one grey level at the configured rate; pixel (0, 0) counts them."""

    def __init__(self, config: TestPatternCameraConfig) -> None:
        super().__init__(config)
        self.config = config
        self.count = 0
        self.connected = False
        self.next_due = 0.0

    @property
    def is_connected(self) -> bool:
        return self.connected

    @staticmethod
    def find_cameras() -> list:
        return []

    def connect(self, warmup: bool = True) -> None:
        self.connected = True
        self.next_due = time.monotonic()

    def read(self):
        return self.async_read()

    def async_read(self, timeout_ms: float = 200):
        time.sleep(max(0.0, self.next_due - time.monotonic()))
        self.next_due += 1 / self.config.fps
        frame = np.full((self.config.height, self.config.width, 3), self.config.level, dtype=np.uint8)
        frame[0, 0] = self.count % 256
        self.count += 1
        return frame

    def disconnect(self) -> None:
        self.connected = False
'''


def test_a_camera_from_an_installed_lerobot_camera_package_delivers_frames(installed_package) -> None:
    installed_package(
        "lerobot_camera_test_pattern",
        "from .config_test_pattern import TestPatternCameraConfig\nfrom .test_pattern import TestPatternCamera\n",
        files={"config_test_pattern.py": PATTERN_CONFIG, "test_pattern.py": PATTERN_CAMERA},
        importable=True,
    )
    config = SensorReaderConfig.model_validate(
        {
            "sensor_id": "pattern",
            "backend": "lerobot_camera",
            "width": WIDTH,
            "height": HEIGHT,
            "fps": 30,
            "encoding": "rgb8",
            "backend_params": {"type": "test_pattern", "level": 77},
        }
    )
    reader = build(config)
    with reader:
        first = next_frame(reader, None)
        second = next_frame(reader, first)
    assert first.data.shape == (HEIGHT, WIDTH, 3)
    assert int(first.data[1, 1, 0]) == 77
    assert int(second.data[0, 0, 0]) > int(first.data[0, 0, 0]), "a new frame from the plugin's camera, not a repeat"
    assert second.stamp_ns > first.stamp_ns
