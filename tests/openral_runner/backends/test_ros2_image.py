"""ROS 2 image backend: message conversion (pure, always tested) and the rclpy reader (needs ROS 2)."""

from __future__ import annotations

import array
import importlib
from types import SimpleNamespace

import numpy as np
import pytest

from openral_core import FrameEncoding, ROSConfigError, ROSDependencyMissing, SensorReaderConfig
from openral_runner.backends.ros2.convert import image_to_frame, ros_stamp_to_monotonic_ns, stamp_to_ns
from openral_runner.backends.ros2.params import Ros2ImageParams
from openral_runner.sensor_reader import validate_backend_params


def message(width: int, height: int, encoding: str, step: int, data: bytes | array.array) -> SimpleNamespace:
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=12, nanosec=500), frame_id="cam_optical"),
        width=width,
        height=height,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=data,
    )


def test_padded_bgr_rows_give_exact_pixels_without_copy() -> None:
    width, height, step = 5, 3, 16  # 15 bytes of pixels per row, padded to 16
    raw = np.arange(step * height, dtype=np.uint8)
    buffer = array.array("B", raw.tobytes())  # rclpy hands over an array.array
    frame = image_to_frame(message(width, height, "bgr8", step, buffer), sensor_id="cam", stamp_ns=7, seq=3)
    pixels = frame.as_array()
    expected = raw.reshape(height, step)[:, : width * 3].reshape(height, width, 3)
    assert pixels.shape == (height, width, 3)
    assert np.array_equal(pixels, expected)
    assert np.shares_memory(pixels, np.frombuffer(buffer, np.uint8))
    assert frame.encoding is FrameEncoding.BGR8
    assert frame.frame_id == "cam_optical"


def test_mono16_and_unsupported_encodings() -> None:
    data = np.array([[1, 2], [3, 65535]], dtype="<u2").tobytes()
    frame = image_to_frame(message(2, 2, "16UC1", 4, data), sensor_id="depth", stamp_ns=1, seq=0)
    assert frame.as_array().tolist() == [[1, 2], [3, 65535]]
    with pytest.raises(ROSConfigError, match="bayer_rggb8"):
        image_to_frame(message(2, 2, "bayer_rggb8", 2, bytes(4)), sensor_id="cam", stamp_ns=1, seq=0)


def test_header_stamp_keeps_its_age_on_the_monotonic_clock() -> None:
    header = stamp_to_ns(SimpleNamespace(sec=100, nanosec=250_000_000))
    assert header == 100_250_000_000
    # The message was stamped 30 ms before "now" on the ROS clock.
    mono = ros_stamp_to_monotonic_ns(header, ros_now_ns=header + 30_000_000, monotonic_now_ns=5_000_000_000)
    assert mono == 5_000_000_000 - 30_000_000


def test_backend_params_are_checked_without_ros2_and_errors_name_the_sensor() -> None:
    good = SensorReaderConfig(sensor_id="wrist", backend="ros2_image", backend_params={"topic": "/wrist/image_raw"})
    params = validate_backend_params(Ros2ImageParams, good, backend="ros2_image")
    assert (params.topic, params.qos) == ("/wrist/image_raw", "sensor_data")
    bad = good.model_copy(update={"backend_params": {"topic": "/wrist/image_raw", "qos": "best"}})
    with pytest.raises(ROSConfigError) as info:
        validate_backend_params(Ros2ImageParams, bad, backend="ros2_image")
    assert info.value.field == "sensors[wrist].backend_params.qos"
    assert "reliable" in str(info.value)


def test_without_ros2_the_error_says_to_source_it_not_to_install_an_extra() -> None:
    try:
        import rclpy  # noqa: F401, PLC0415
    except ImportError:
        pass
    else:
        pytest.skip("rclpy is installed: the backend imports")
    with pytest.raises(ROSDependencyMissing) as info:
        importlib.import_module("openral_runner.backends.ros2.reader")
    assert info.value.extra is None
    assert "source a ROS 2 distribution" in str(info.value)
    assert "uv sync" not in str(info.value)


def test_reader_needs_rclpy() -> None:
    pytest.importorskip("rclpy", reason="rclpy needs a ROS 2 installation, which cannot be installed here")
    from openral_runner.backends.ros2.reader import Ros2ImageSensorReader  # noqa: PLC0415

    reader = Ros2ImageSensorReader(sensor_id="cam", topic="/camera/image_raw")
    assert not reader.is_open
