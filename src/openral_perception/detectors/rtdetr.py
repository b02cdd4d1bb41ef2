"""The RT-DETR / D-FINE detector signature in numpy: the model's input from an RGB frame, detections from its outputs.

Input ``images`` ``(1, 3, H, W)`` float32 RGB in ``[0, 1]``; outputs ``logits`` ``(1, N, C)``
(one score per class, before the sigmoid) and ``boxes`` ``(1, N, 4)`` (centre x, centre y, width,
height, normalised to the input). Whatever runs the model (ONNX Runtime on the CPU here, other
tiers elsewhere) shares this code, so boxes mean the same everywhere.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import structlog

from openral_core import ROSConfigError
from openral_core.perception import ObjectDetection2D, ObjectsMetadata, PixelBox

_log = structlog.get_logger(__name__)

LETTERBOX_GREY = 114
"""The padding level of a letterboxed input (the YOLO / RT-DETR convention)."""

Content = tuple[float, float, float, float]
"""Where the frame lies in the model's input, normalised ``(x0, y0, x1, y1)``."""


def identify_rtdetr_outputs(named_shapes: Sequence[tuple[str, Sequence[Any]]]) -> tuple[str, str]:
    """``(logits name, boxes name)`` among a model's outputs.

    Of the 3-D outputs, the one whose last dimension is 4 holds the boxes; when both (or neither)
    end in 4, the first is taken as logits and the second as boxes.

    Raises:
        ROSConfigError: Fewer than two 3-D outputs.
    """
    three_d = [(name, tuple(shape)) for name, shape in named_shapes if len(shape) == 3]
    if len(three_d) < 2:
        raise ROSConfigError(
            f"an RT-DETR detector has two 3-D outputs (logits, boxes); this one has {list(named_shapes)}",
            field="model",
        )
    ends_in_4 = [name for name, shape in three_d if shape[-1] == 4]
    if len(ends_in_4) == 1:
        boxes = ends_in_4[0]
        logits = next(name for name, _shape in three_d if name != boxes)
        return logits, boxes
    return three_d[0][0], three_d[1][0]


def model_input(
    rgb: np.ndarray, input_size: tuple[int, int], resize: Literal["stretch", "letterbox"] | str = "stretch"
) -> tuple[np.ndarray, Content]:
    """The model's input for an ``(H, W, 3)`` RGB frame, and where the frame lies in it.

    ``stretch`` samples the frame onto the whole input (nearest neighbour); ``letterbox`` keeps
    its aspect and pads the rest grey (:data:`LETTERBOX_GREY`).
    """
    net_h, net_w = input_size
    height, width = rgb.shape[:2]
    if resize == "stretch":
        rows = (np.arange(net_h) * height // net_h).astype(np.intp)
        cols = (np.arange(net_w) * width // net_w).astype(np.intp)
        image = rgb[rows][:, cols]
        content: Content = (0.0, 0.0, 1.0, 1.0)
    else:
        scale = min(net_h / height, net_w / width)
        new_h, new_w = max(1, math.floor(height * scale)), max(1, math.floor(width * scale))
        rows = (np.arange(new_h) * height // new_h).astype(np.intp)
        cols = (np.arange(new_w) * width // new_w).astype(np.intp)
        image = np.full((net_h, net_w, 3), LETTERBOX_GREY, dtype=np.uint8)
        top, left = (net_h - new_h) // 2, (net_w - new_w) // 2
        image[top : top + new_h, left : left + new_w] = rgb[rows][:, cols]
        content = (left / net_w, top / net_h, (left + new_w) / net_w, (top + new_h) / net_h)
    tensor = np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32) / 255.0
    return tensor, content


def postprocess_rtdetr(
    logits: np.ndarray,
    boxes: np.ndarray,
    *,
    labels: Sequence[str],
    model_id: str,
    score_threshold: float,
    frame_width: int,
    frame_height: int,
    content: Content = (0.0, 0.0, 1.0, 1.0),
) -> ObjectsMetadata | None:
    """Detections from raw outputs: sigmoid, best class, threshold, boxes in frame pixels, most confident first.

    Args:
        logits: ``(N, C)`` or ``(1, N, C)``.
        boxes: ``(N, 4)`` or ``(1, N, 4)``, normalised ``cx, cy, w, h`` of the model's input.
        content: Where the frame lies in the model's input (not the whole input when it was letterboxed).

    Returns:
        ``None`` when nothing passes the threshold.
    """
    scores_all = 1.0 / (1.0 + np.exp(-np.asarray(logits, dtype=np.float64).reshape(-1, np.shape(logits)[-1])))
    cxcywh = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    classes = scores_all.argmax(axis=1)
    scores = scores_all[np.arange(len(classes)), classes]
    cx0, cy0, cx1, cy1 = content
    detections: list[ObjectDetection2D] = []
    for index in np.flatnonzero(scores >= score_threshold):
        cls = int(classes[index])
        if cls >= len(labels):
            _log.warning("detector class index beyond the labels", index=cls, labels=len(labels))
            continue
        cx, cy, w, h = cxcywh[index]
        corners = np.array([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2])
        if not np.all(np.isfinite(corners)):
            continue
        x0, x1 = ((corners[[0, 2]] - cx0) / (cx1 - cx0)).clip(0.0, 1.0) * frame_width
        y0, y1 = ((corners[[1, 3]] - cy0) / (cy1 - cy0)).clip(0.0, 1.0) * frame_height
        if x1 - x0 < 1.0 or y1 - y0 < 1.0:  # degenerate: nothing a person could see
            continue
        detections.append(
            ObjectDetection2D(
                label=labels[cls],
                confidence=float(scores[index]),
                box=PixelBox(x0=float(x0), y0=float(y0), x1=float(x1), y1=float(y1)),
            )
        )
    if not detections:
        return None
    detections.sort(key=lambda detection: detection.confidence, reverse=True)
    return ObjectsMetadata(model_id=model_id, detections=detections)
