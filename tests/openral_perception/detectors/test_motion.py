"""The motion detector: by cells on the grey image, noise neither fires nor stretches the box, per camera."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from openral_core import ROSConfigError, SensorFrame
from openral_core.perception import MotionMetadata
from openral_perception.detectors.motion import MotionDetector
from openral_perception.frame import DetectorFrame

H, W = 48, 64


def grey_frame(level: int, sensor_id: str = "cam") -> DetectorFrame:
    return DetectorFrame.from_array(np.full((H, W, 3), level, dtype=np.uint8), sensor_id=sensor_id)


frames = st.one_of(
    st.integers(0, 255).map(lambda level: np.full((H, W, 3), level, dtype=np.uint8)),
    st.integers(0, 2**32 - 1).map(lambda seed: np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)),
)


@settings(max_examples=60, deadline=None)
@given(first=frames, second=frames)
def test_any_frame_gives_an_event_in_range_or_none(first, second):
    motion = MotionDetector()
    assert motion.detect(DetectorFrame.from_array(first, sensor_id="cam")) is None  # nothing to compare with yet
    found = motion.detect(DetectorFrame.from_array(second, sensor_id="cam"))
    if found is not None:
        assert 0 < found.changed_fraction <= 1
        assert 0 <= found.box.x0 < found.box.x1 <= W
        assert 0 <= found.box.y0 < found.box.y1 <= H
    still = MotionDetector()
    still.detect(DetectorFrame.from_array(second, sensor_id="cam"))
    assert still.detect(DetectorFrame.from_array(second.copy(), sensor_id="cam")) is None


def test_one_changed_pixel_neither_fires_nor_widens_the_box():
    detector = MotionDetector()
    base = np.full((H, W, 3), 100, dtype=np.uint8)
    detector.detect(DetectorFrame.from_array(base, sensor_id="cam"))
    speck = base.copy()
    speck[H - 1, W - 1] = 255
    assert detector.detect(DetectorFrame.from_array(speck, sensor_id="cam")) is None
    moved = speck.copy()
    moved[8:24, 16:32] = 250  # a real object: two cells by two
    found = detector.detect(DetectorFrame.from_array(moved, sensor_id="cam"))
    assert isinstance(found, MotionMetadata)
    assert (found.box.x0, found.box.y0, found.box.x1, found.box.y1) == (16, 8, 32, 24)
    another = moved.copy()
    another[0, 0] = 0  # and a far noisy pixel at the same time
    another[8:24, 16:32] = 10
    found = detector.detect(DetectorFrame.from_array(another, sensor_id="cam"))
    assert found is not None
    assert (found.box.x0, found.box.y0, found.box.x1, found.box.y1) == (16, 8, 32, 24)


def test_each_sensor_is_compared_with_its_own_previous_frame():
    detector = MotionDetector()
    detector.detect(grey_frame(0, "left"))
    detector.detect(grey_frame(255, "right"))
    assert detector.detect(grey_frame(0, "left")) is None
    assert detector.detect(grey_frame(0, "right")) is not None


@pytest.mark.parametrize("width", [W, 7])  # 7 * 3 bytes: rows that GStreamer pads to 24
def test_a_frame_with_padded_rows_reads_as_the_packed_one(width):
    first = np.random.default_rng(width).integers(40, 48, (H, width, 3), dtype=np.uint8)  # a dim, textured view
    second = first.copy()
    second[: H // 2] += 180  # its top half lights up
    packed = MotionDetector()
    packed.detect(DetectorFrame.from_array(first, sensor_id="cam"))
    wanted = packed.detect(DetectorFrame.from_array(second, sensor_id="cam"))
    assert wanted is not None
    padded = MotionDetector()
    for pixels in (first, second):
        stride = -(-width * 3 // 4) * 4
        rows = np.full((H, stride), 255, dtype=np.uint8)  # padding that must not count
        rows[:, : width * 3] = pixels.reshape(H, width * 3)
        frame = SensorFrame(
            sensor_id="cam", stamp_ns=0, width=width, height=H, encoding="bgr8", row_stride=stride, data=rows.tobytes()
        )
        found = padded.detect(DetectorFrame(frame))
    assert found == wanted


def test_a_wrong_setting_is_named():
    with pytest.raises(ROSConfigError, match="threshold"):
        MotionDetector.from_config({"threshold": 300})
    with pytest.raises(ROSConfigError, match="unknown key 'cells'"):
        MotionDetector.from_config({"cells": 4})
    assert MotionDetector.from_config({"cell": 4}).params.cell == 4
