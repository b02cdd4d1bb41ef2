"""``DetectorRunner``: a ``kind: detector`` rSkill on a live camera, as a branch of its tee.

The detector is built from the manifest (:func:`~openral_perception.detectors.factory.build_manifest_detector`)
and runs on a branch :class:`~openral_runner.backends.gstreamer.tee_manager.TeeManager` attaches
behind the tee's leaky queue (``videoconvert`` to BGR, an appsink keeping only the newest frame),
so however slow it is the policy's leg never waits. Each detection is handed to ``on_detection``.

This is the library door to detectors (no deployment field builds it); a deployment runs them
through the ``perception`` observer or a GStreamer sensor's ``backend_params.perception`` (see
:mod:`openral_perception`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import structlog

from openral_core import ROSRuntimeError, SensorFrame
from openral_core.perception import ObjectsMetadata
from openral_perception.detectors.factory import build_manifest_detector
from openral_perception.frame import DetectorFrame
from openral_rskill.manifest import RSkillManifest
from openral_runner.backends.gstreamer.pipeline import TEE_NAME
from openral_runner.backends.gstreamer.sample import AppsinkTap, SampleFrames
from openral_runner.backends.gstreamer.tee_manager import BranchHandle, TeeManager

_log = structlog.get_logger(__name__)
_ids = itertools.count()


class DetectorRunner:
    """Runs a detector manifest on ``pipeline``'s tee and calls ``on_detection`` with what it finds.

    Args:
        pipeline: A pipeline with a camera tee (``enable_event_tee`` or ``enable_ros_tee``).
        manifest: A ``kind: detector`` rSkill manifest.
        onnx_path: The model, when not the manifest's own.
        sensor_id: Names the camera in the detections.
        on_detection: Called (on the branch's streaming thread) with each frame's objects.
        tier: Force a tier (default: the CPU).
    """

    def __init__(
        self,
        pipeline: Any,
        manifest: RSkillManifest,
        *,
        sensor_id: str,
        on_detection: Callable[[ObjectsMetadata], None],
        onnx_path: str | None = None,
        tee_name: str = TEE_NAME,
        tier: str | None = None,
    ) -> None:
        self.detector, self.tier = build_manifest_detector(manifest, onnx_path=onnx_path, tier=tier)
        self.sensor_id = sensor_id
        self.on_detection = on_detection
        self.tees = TeeManager(pipeline, tee_name=tee_name)
        self.frames = 0
        self._past_errors = 0
        self._handle: BranchHandle | None = None
        self._tap: AppsinkTap | None = None

    @property
    def errors(self) -> int:
        """Frames the branch could not read or the detector (or ``on_detection``) failed on."""
        return self._past_errors + (0 if self._tap is None else self._tap.errors)

    def start(self) -> None:
        """Attach the detector's branch. Idempotent."""
        if self._handle is not None:
            return
        sink_name = f"openral_detector_sink_{next(_ids)}"
        handle = self.tees.attach(
            f"videoconvert ! video/x-raw,format=BGR ! appsink name={sink_name} emit-signals=true sync=false "
            "max-buffers=1 drop=true",
            name=f"{sink_name}_branch",
        )
        sink = handle.bin.get_by_name(sink_name)
        if sink is None:
            self.tees.detach(handle)
            raise ROSRuntimeError(f"the detector branch has no appsink {sink_name!r}")
        self._handle = handle
        self._tap = AppsinkTap(sink, SampleFrames(self.sensor_id), self._on_frame)

    def stop(self) -> None:
        """Detach the branch and release the detector. Idempotent."""
        if self._tap is not None:
            self._tap.detach()
            self._past_errors += self._tap.errors
        if self._handle is not None:
            self.tees.detach(self._handle)
        self._handle = self._tap = None

    def _on_frame(self, frame: SensorFrame) -> None:
        """One frame of the branch (streaming thread): detect, hand over what was found."""
        self.frames += 1
        found = self.detector.detect(DetectorFrame(frame))
        if isinstance(found, ObjectsMetadata):
            self.on_detection(found)
