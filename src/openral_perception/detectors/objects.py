"""``objects``: object detection on the CPU with ONNX Runtime, for models with the RT-DETR / D-FINE signature.

The model takes RGB (:mod:`~openral_perception.detectors.rtdetr` describes the signature and
decodes it), so the detector reads the frame's RGB view: no channel flipping of its own. It takes a
frame as the publisher hands it over (a :class:`~openral_perception.frame.DetectorFrame`) or as an
appsink does (``detect(frame_bgr, width, height, sensor_id)``, the specification's form, see
:mod:`~openral_perception.detectors.buffers`). Tiers that
need hardware or weights from a hub (``nvinfer``, ``nvmm_aggregator``, ``vlm_sidecar``,
``zeroshot_hf``) are refused with what they need (:mod:`~openral_perception.detectors.tier`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from openral_core import ROSConfigError, ROSDependencyMissing
from openral_core.config import validate_model
from openral_core.perception import ObjectsMetadata
from openral_perception.detectors.buffers import BufferDetector
from openral_perception.detectors.objects_params import ObjectsParams, ObjectsSettings, objects_settings
from openral_perception.detectors.rtdetr import identify_rtdetr_outputs, model_input, postprocess_rtdetr
from openral_perception.detectors.tier import DetectorTier, require_runnable
from openral_perception.frame import DetectorFrame

try:
    import onnxruntime as ort
except ImportError as exc:
    raise ROSDependencyMissing("onnxruntime", extra="policy", needed_for="the ONNX object detector") from exc


class ObjectsDetector(BufferDetector[ObjectsMetadata]):
    """An :class:`~openral_perception.detectors.base.EventDetector` running an ONNX model on the CPU.

    Args:
        onnx_path: The model.
        labels: Class names, in the model's class order.
        model_id: Named in the events.
        input_size: The model's ``(height, width)`` (read from the model when it is fixed there).
        score_threshold: Detections below it are dropped.
        device: Where the model runs: ``cpu``, the one device of this tier.
        resize: ``stretch`` the frame to the input, or ``letterbox`` it (aspect kept, padded grey).
        intra_op_threads: ONNX Runtime's threads (one: the robot's machine has other work).

    Raises:
        ROSConfigError: No labels, a threshold outside [0, 1], a device other than the CPU, no such
            file, or a file that is not an RT-DETR detector (each naming its parameter).
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
        device: str = "cpu",
        resize: Literal["stretch", "letterbox"] | str = "stretch",
        intra_op_threads: int = 1,
    ) -> None:
        if not labels:
            raise ROSConfigError("a detector needs its class names", field="labels")
        if not 0 <= score_threshold <= 1:
            raise ROSConfigError(f"{score_threshold} is outside [0, 1]", field="score_threshold")
        if device != "cpu":
            raise ROSConfigError(
                f"device {device!r}: this tier runs ONNX Runtime on the CPU", field="device", hint="device='cpu'"
            )
        if resize not in ("stretch", "letterbox"):
            raise ROSConfigError(f"unknown resize {resize!r}", field="resize", hint="stretch or letterbox")
        path = Path(onnx_path)
        if not path.is_file():
            raise ROSConfigError(f"no model file {path}", field="model")
        options = ort.SessionOptions()
        options.intra_op_num_threads = intra_op_threads
        options.inter_op_num_threads = 1
        try:
            self._session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types for a bad file
            raise ROSConfigError(f"cannot load {path}: {exc}", field="model") from exc
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise ROSConfigError(f"{path.name} has {len(inputs)} inputs; an RT-DETR model has one", field="model")
        self._input = inputs[0].name
        shape = inputs[0].shape
        fixed = len(shape) == 4 and all(isinstance(d, int) for d in shape[2:])
        self.input_size = (int(shape[2]), int(shape[3])) if fixed else input_size
        outputs = [(o.name, o.shape) for o in self._session.get_outputs()]
        self._logits, self._boxes = identify_rtdetr_outputs(outputs)
        self.labels = list(labels)
        self.model_id = model_id
        self.score_threshold = score_threshold
        self.device = device
        self.resize = resize

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, base_dir: Path | None = None) -> ObjectsDetector:
        """Plugin constructor (detector ``objects``); ``params`` are :class:`~.objects_params.ObjectsParams`."""
        return cls.from_settings(objects_settings(validate_model(ObjectsParams, dict(params)), base_dir=base_dir))

    @classmethod
    def from_settings(cls, settings: ObjectsSettings) -> ObjectsDetector:
        """The detector of resolved settings (a model file and how to read it)."""
        return cls(
            str(settings.model),
            labels=settings.labels,
            model_id=settings.model_id,
            input_size=settings.input_size,
            score_threshold=settings.score_threshold,
            resize=settings.resize,
        )

    def detect_frame(self, frame: DetectorFrame) -> ObjectsMetadata | None:
        """The objects in ``frame``, boxes in its pixels (``detect`` also takes a BGR buffer and its size)."""
        tensor, content = model_input(frame.rgb, self.input_size, self.resize)
        logits, boxes = self._session.run([self._logits, self._boxes], {self._input: tensor})
        return postprocess_rtdetr(
            logits,
            boxes,
            labels=self.labels,
            model_id=self.model_id,
            score_threshold=self.score_threshold,
            frame_width=frame.width,
            frame_height=frame.height,
            content=content,
        )

    def summarise(self, metadata: ObjectsMetadata) -> str:
        counts: dict[str, int] = {}
        for detection in metadata.detections:
            counts[detection.label] = counts.get(detection.label, 0) + 1
        return ", ".join(f"{n}x {label}" for label, n in counts.items())


def make_objects_detector(
    onnx_path: str, *, labels: Sequence[str], model_id: str, tier: DetectorTier | str | None = None, **kwargs: Any
) -> ObjectsDetector:
    """The detector of ``tier`` (default: the CPU, the one tier every machine has).

    Raises:
        ROSConfigError: A tier this build cannot run, saying what it needs.
    """
    require_runnable(DetectorTier.CPU_ONNX if tier is None else DetectorTier(tier), field="tier")
    return ObjectsDetector(onnx_path, labels=labels, model_id=model_id, **kwargs)


__all__ = ["ObjectsDetector", "make_objects_detector"]
