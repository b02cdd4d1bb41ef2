"""The detectors' frame view: the frame's own colour views, each form made once, nothing it cannot show."""

from __future__ import annotations

import numpy as np
import pytest

from openral_core import SensorFrame
from openral_perception.frame import DetectorFrame, is_viewable


def _frame(encoding: str, pixels: np.ndarray) -> SensorFrame:
    height, width = pixels.shape[:2]
    return SensorFrame(sensor_id="cam", stamp_ns=7, width=width, height=height, encoding=encoding, data=pixels)


def test_an_rgb_frame_is_viewed_in_both_orders_without_a_copy_and_grey_once():
    rgb = np.random.default_rng(0).integers(0, 256, (4, 5, 3), dtype=np.uint8)
    view = DetectorFrame(_frame("rgb8", rgb))
    assert (view.sensor_id, view.stamp_ns, view.width, view.height) == ("cam", 7, 5, 4)
    assert np.shares_memory(view.rgb, rgb)
    assert np.shares_memory(view.bgr, rgb)
    np.testing.assert_array_equal(view.bgr, rgb[..., ::-1])
    np.testing.assert_array_equal(view.rgb, rgb)
    grey = view.grey
    assert grey is view.grey  # cached: the second detector gets the same array
    r, g, b = (rgb[..., i].astype(np.uint32) for i in range(3))
    np.testing.assert_array_equal(grey, ((29 * b + 150 * g + 77 * r + 128) >> 8).astype(np.uint8))


def test_a_grey_frame_is_its_own_grey_and_a_grey_colour():
    mono = np.arange(12, dtype=np.uint8).reshape(3, 4)
    view = DetectorFrame.from_array(mono, sensor_id="ir")
    assert view.frame.encoding == "mono8"
    assert np.shares_memory(view.grey, mono)
    assert view.rgb.shape == (3, 4, 3)
    assert (view.bgr[..., 1] == mono).all()


@pytest.mark.parametrize(
    "frame",
    [
        SensorFrame(sensor_id="cam", stamp_ns=0, width=2, height=2, encoding="jpeg", data=b"\xff\xd8"),
        SensorFrame(sensor_id="cam", stamp_ns=0, width=2, height=2, encoding="mono16", data=bytes(8)),
        SensorFrame(sensor_id="cam", stamp_ns=0, width=2, height=2, topic="/camera/image"),
    ],
)
def test_frames_without_8_bit_pixels_inline_are_not_viewable(frame):
    assert not is_viewable(frame)
    with pytest.raises(ValueError, match="detectors look at"):
        DetectorFrame(frame)


def test_an_array_that_is_not_an_image_is_refused():
    with pytest.raises(ValueError, match="uint8"):
        DetectorFrame.from_array(np.zeros((4, 4, 3), dtype=np.float32), sensor_id="cam")
