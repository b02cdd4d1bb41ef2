"""Object detection on the CPU with ONNX Runtime, for models with the RT-DETR / D-FINE signature.

Input ``images`` ``(1, 3, H, W)`` float32 RGB in ``[0, 1]``; outputs ``logits`` ``(1, N, C)``
(one score per class, before the sigmoid) and ``boxes`` ``(1, N, 4)`` (centre x, centre y, width,
height, normalised to the input). Decoding is the same whatever runs the model
(:func:`postprocess_rtdetr`), so other tiers share it. Tiers that need hardware or weights from a
hub (``nvinfer``, ``nvmm_aggregator``, ``vlm_sidecar``, ``zeroshot_hf``) are refused with what
they need.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable, Sequence
from enum import StrEnum
from pathlib import Path
from typing import Any, Literal

import numpy as np
import structlog

from openral_core import ROSConfigError, ROSDependencyMissing
from openral_core.perception import ObjectDetection2D, ObjectsMetadata, PixelBox
from openral_runner.backends.gstreamer.perception_tee import FrameBuffer, frame_pixels

try:
    import onnxruntime as ort
except ImportError as exc:
    raise ROSDependencyMissing("onnxruntime", extra="policy", needed_for="the ONNX object detector") from exc

_log = structlog.get_logger(__name__)


class DetectorTier(StrEnum):
    """Where an object detector runs."""

    CPU_ONNX = "cpu_onnx"
    NVINFER = "nvinfer"
    NVMM_AGGREGATOR = "nvmm_aggregator"
    VLM_SIDECAR = "vlm_sidecar"
    ZEROSHOT_HF = "zeroshot_hf"


_NEEDS: dict[DetectorTier, str] = {
    DetectorTier.NVINFER: "DeepStream's nvinfer element and an NVIDIA GPU",
    DetectorTier.NVMM_AGGREGATOR: "a Jetson (NVMM buffers), TensorRT and cuda-python",
    DetectorTier.VLM_SIDECAR: "an open-vocabulary VLM sidecar and its weights from a model hub",
    DetectorTier.ZEROSHOT_HF: "PyTorch, transformers and zero-shot detector weights from the Hugging Face hub",
}


def select_detector_tier(
    *, has_nvinfer: Callable[[], bool] | None = None, on_tegra: Callable[[], bool] | None = None
) -> DetectorTier:
    """The fastest tier this machine has: ``nvinfer`` where DeepStream is installed, NVMM on a Jetson, else the CPU."""
    nvinfer = has_nvinfer or (lambda: shutil.which("gst-inspect-1.0") is not None and _gst_has("nvinfer"))
    tegra = on_tegra or (lambda: Path("/etc/nv_tegra_release").exists())
    if nvinfer():
        return DetectorTier.NVINFER
    if tegra():
        return DetectorTier.NVMM_AGGREGATOR
    return DetectorTier.CPU_ONNX


def _gst_has(element: str) -> bool:
    from openral_runner.backends.gstreamer.pipeline import inspect_element_present  # noqa: PLC0415

    return inspect_element_present(element)


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
            field="objects.model",
        )
    ends_in_4 = [name for name, shape in three_d if shape[-1] == 4]
    if len(ends_in_4) == 1:
        boxes = ends_in_4[0]
        logits = next(name for name, _shape in three_d if name != boxes)
        return logits, boxes
    return three_d[0][0], three_d[1][0]


def postprocess_rtdetr(
    logits: np.ndarray,
    boxes: np.ndarray,
    *,
    labels: Sequence[str],
    model_id: str,
    score_threshold: float,
    frame_width: int,
    frame_height: int,
    content: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0),
) -> ObjectsMetadata | None:
    """Detections from raw outputs: sigmoid, best class, threshold, boxes in frame pixels, most confident first.

    Args:
        logits: ``(N, C)`` or ``(1, N, C)``.
        boxes: ``(N, 4)`` or ``(1, N, 4)``, normalised ``cx, cy, w, h`` of the model's input.
        content: Where the frame lies in the model's input, normalised ``(x0, y0, x1, y1)`` (not
            the whole input when it was letterboxed).

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


class ObjectsDetector:
    """An :class:`~openral_runner.backends.gstreamer.perception_tee.EventDetector` running an ONNX model on the CPU.

    Args:
        onnx_path: The model.
        labels: Class names, in the model's class order.
        model_id: Named in the events.
        input_size: The model's ``(height, width)`` (read from the model when it is fixed there).
        score_threshold: Detections below it are dropped.
        resize: ``stretch`` the frame to the input, or ``letterbox`` it (aspect kept, padded grey).
        intra_op_threads: ONNX Runtime's threads (one: the robot's machine has other work).
    """

    kind = "objects"

    def __init__(
        self,
        onnx_path: str,
        *,
        labels: Sequence[str],
        model_id: str,
        input_size: tuple[int, int] = (640, 640),
        score_threshold: float = 0.5,
        resize: Literal["stretch", "letterbox"] | str = "stretch",
        intra_op_threads: int = 1,
    ) -> None:
        if not labels:
            raise ROSConfigError("a detector needs its class names", field="objects.labels")
        if not 0 <= score_threshold <= 1:
            raise ROSConfigError(f"{score_threshold} is outside [0, 1]", field="objects.score_threshold")
        if resize not in ("stretch", "letterbox"):
            raise ROSConfigError(f"unknown resize {resize!r}", field="objects.resize", hint="stretch or letterbox")
        path = Path(onnx_path)
        if not path.is_file():
            raise ROSConfigError(f"no model file {path}", field="objects.model")
        options = ort.SessionOptions()
        options.intra_op_num_threads = intra_op_threads
        options.inter_op_num_threads = 1
        try:
            self._session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types for a bad file
            raise ROSConfigError(f"cannot load {path}: {exc}", field="objects.model") from exc
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise ROSConfigError(
                f"{path.name} has {len(inputs)} inputs; an RT-DETR model has one", field="objects.model"
            )
        self._input = inputs[0].name
        shape = inputs[0].shape
        fixed = len(shape) == 4 and all(isinstance(d, int) for d in shape[2:])
        self.input_size = (int(shape[2]), int(shape[3])) if fixed else input_size
        outputs = [(o.name, o.shape) for o in self._session.get_outputs()]
        self._logits, self._boxes = identify_rtdetr_outputs(outputs)
        self.labels = list(labels)
        self.model_id = model_id
        self.score_threshold = score_threshold
        self.resize = resize

    def prepare(self, frame_bgr: np.ndarray) -> tuple[np.ndarray, tuple[float, float, float, float]]:
        """The model's input for a BGR frame, and where the frame lies in it (normalised)."""
        net_h, net_w = self.input_size
        height, width = frame_bgr.shape[:2]
        rgb = frame_bgr[..., ::-1] if frame_bgr.ndim == 3 else np.repeat(frame_bgr[..., None], 3, axis=2)
        if self.resize == "stretch":
            rows = (np.arange(net_h) * height // net_h).astype(np.intp)
            cols = (np.arange(net_w) * width // net_w).astype(np.intp)
            image = rgb[rows][:, cols]
            content = (0.0, 0.0, 1.0, 1.0)
        else:
            scale = min(net_h / height, net_w / width)
            new_h, new_w = max(1, math.floor(height * scale)), max(1, math.floor(width * scale))
            rows = (np.arange(new_h) * height // new_h).astype(np.intp)
            cols = (np.arange(new_w) * width // new_w).astype(np.intp)
            image = np.full((net_h, net_w, 3), 114, dtype=np.uint8)
            top, left = (net_h - new_h) // 2, (net_w - new_w) // 2
            image[top : top + new_h, left : left + new_w] = rgb[rows][:, cols]
            content = (left / net_w, top / net_h, (left + new_w) / net_w, (top + new_h) / net_h)
        tensor = np.ascontiguousarray(image.transpose(2, 0, 1)[None], dtype=np.float32) / 255.0
        return tensor, content

    def detect(self, frame_bgr: FrameBuffer, width: int, height: int, sensor_id: str) -> ObjectsMetadata | None:
        """The objects in a ``width`` × ``height`` BGR frame, flat (an appsink's buffer) or shaped."""
        tensor, content = self.prepare(frame_pixels(frame_bgr, width, height))
        logits, boxes = self._session.run([self._logits, self._boxes], {self._input: tensor})
        return postprocess_rtdetr(
            logits,
            boxes,
            labels=self.labels,
            model_id=self.model_id,
            score_threshold=self.score_threshold,
            frame_width=width,
            frame_height=height,
            content=content,
        )

    def summarise(self, metadata: ObjectsMetadata) -> str:
        counts: dict[str, int] = {}
        for detection in metadata.detections:
            counts[detection.label] = counts.get(detection.label, 0) + 1
        return ", ".join(f"{n}x {label}" for label, n in counts.items())


def make_objects_detector(
    onnx_path: str, *, labels: Sequence[str], model_id: str, tier: DetectorTier | None = None, **kwargs: Any
) -> ObjectsDetector:
    """The detector of ``tier`` (default: the CPU, the one tier every machine has).

    Raises:
        ROSConfigError: A tier this build cannot run, saying what it needs.
    """
    chosen = DetectorTier.CPU_ONNX if tier is None else DetectorTier(tier)
    if chosen is not DetectorTier.CPU_ONNX:
        raise ROSConfigError(
            f"the {chosen.value} detector tier needs {_NEEDS[chosen]}; openral runs ONNX detectors on the CPU",
            field="objects.tier",
            hint="use tier cpu_onnx",
        )
    return ObjectsDetector(onnx_path, labels=labels, model_id=model_id, **kwargs)
