"""The RT-DETR signature in numpy: outputs told apart, detections decoded, the input stretched or letterboxed."""

from __future__ import annotations

import numpy as np
import pytest

from openral_core import ROSConfigError
from openral_core.perception import PixelBox
from openral_perception.detectors.rtdetr import LETTERBOX_GREY, identify_rtdetr_outputs, model_input, postprocess_rtdetr


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


def test_the_input_is_rgb_nchw_in_0_1_and_a_letterbox_says_where_the_frame_is():
    rgb = np.zeros((100, 200, 3), dtype=np.uint8)
    rgb[...] = (255, 0, 51)
    tensor, content = model_input(rgb, (64, 64), "stretch")
    assert tensor.shape == (1, 3, 64, 64)
    assert tensor.dtype == np.float32
    assert tensor[0, :, 10, 10] == pytest.approx([1.0, 0.0, 0.2])
    assert content == (0.0, 0.0, 1.0, 1.0)
    tensor, content = model_input(rgb, (64, 64), "letterbox")
    assert content == (0.0, 0.25, 1.0, 0.75)
    assert tensor[0, 0, 0, 0] == pytest.approx(LETTERBOX_GREY / 255)  # the padding above the frame
    assert tensor[0, :, 32, 32] == pytest.approx([1.0, 0.0, 0.2])
