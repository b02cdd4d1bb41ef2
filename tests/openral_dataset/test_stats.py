"""Statistics: a camera's frames sampled as the video decodes them, a bounded sample for any episode length."""

from __future__ import annotations

import numpy as np
import pytest

from openral_core import FrameEncoding, SensorFrame
from openral_dataset import stats

W, H = 32, 24


def _frame(encoding: FrameEncoding, pixels: np.ndarray) -> SensorFrame:
    return SensorFrame(
        sensor_id="cam", stamp_ns=0, width=W, height=H, encoding=encoding, data=np.ascontiguousarray(pixels)
    )


@pytest.mark.parametrize(
    ("encoding", "pixel"),
    [
        (FrameEncoding.RGB8, [10, 20, 30]),
        (FrameEncoding.BGR8, [30, 20, 10]),
        (FrameEncoding.RGBA8, [10, 20, 30, 255]),
        (FrameEncoding.BGRA8, [30, 20, 10, 255]),
        (FrameEncoding.MONO8, 20),
    ],
)
def test_a_sampled_frame_is_rgb_whatever_the_camera_sends(encoding: FrameEncoding, pixel: object) -> None:
    channels = np.asarray(pixel, np.uint8)
    shape = (H, W) if channels.ndim == 0 else (H, W, channels.size)
    sample = stats.FrameSample()
    sample.add(_frame(encoding, np.broadcast_to(channels, shape)), 0)
    (kept,) = sample.frames
    step = stats.IMAGE_SAMPLE_STRIDE
    assert kept.shape == (-(-H // step), -(-W // step), 3)
    assert kept.flags.c_contiguous
    expected = [20, 20, 20] if encoding is FrameEncoding.MONO8 else [10, 20, 30]
    assert (kept == np.asarray(expected, np.uint8)).all()


def test_a_long_episode_keeps_a_bounded_evenly_spaced_sample() -> None:
    sample = stats.FrameSample()
    for index in range(1000):
        pixels = np.zeros((H, W, 3), np.uint8)
        pixels[..., 0], pixels[..., 1] = divmod(index, 256)  # the frame's index, readable in its sample
        sample.add(_frame(FrameEncoding.RGB8, pixels), index)
    kept = [int(f[0, 0, 0]) * 256 + int(f[0, 0, 1]) for f in sample.frames]
    assert stats.IMAGE_SAMPLE_FRAMES <= len(kept) < 2 * stats.IMAGE_SAMPLE_FRAMES
    stride = kept[1]
    assert kept == list(range(0, 1000, stride))
