"""Detectors over an appsink's buffer: the buffer is viewed, not copied, and a call names one frame form."""

from __future__ import annotations

import numpy as np
import pytest

from openral_perception.detectors.buffers import BufferMotionDetector, BufferSceneChangeDetector, buffer_frame
from openral_perception.frame import DetectorFrame

H, W = 6, 5


def test_a_flat_buffer_is_viewed_not_copied_padding_cut_off():
    padded = np.arange(H * 16, dtype=np.uint8)  # rows of 15 bytes padded to 16
    frame = buffer_frame(padded, W, H, "cam")
    assert np.shares_memory(frame.bgr, padded)
    assert frame.bgr.shape == (H, W, 3)
    assert frame.bgr[1, 0, 0] == 16  # the second row starts after the padding
    shaped = np.zeros((H, W, 3), dtype=np.uint8)
    assert np.shares_memory(buffer_frame(shaped, W, H, "cam").bgr, shaped)


@pytest.mark.parametrize("detector", [BufferMotionDetector(), BufferSceneChangeDetector()])
def test_a_call_gives_a_detector_frame_alone_or_a_buffer_with_its_size(detector):
    view = DetectorFrame.from_array(np.zeros((H, W, 3), dtype=np.uint8), sensor_id="cam")
    with pytest.raises(TypeError, match="alone"):
        detector.detect(view, W, H, "cam")
    with pytest.raises(TypeError, match="width, height and sensor_id"):
        detector.detect(bytes(H * W * 3))
    assert detector.detect(view) is None
    assert detector.detect(bytes(H * W * 3), W, H, "cam") is None


def test_a_motion_detector_keeps_its_own_copy_of_the_previous_frame():
    buffer = np.full(H * W * 3, 100, dtype=np.uint8)
    motion = BufferMotionDetector()
    motion.detect(buffer, W, H, "cam")
    buffer[:] = 200  # the appsink reuses its buffer for the next frame
    assert motion.detect(buffer, W, H, "cam") is not None
