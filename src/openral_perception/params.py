"""Settings of the perception observer (or a GStreamer event leg): which detectors, how often, and where events go.

Each detector is an entry ``{kind: <name in openral.detectors>, params: {...}}``; its ``params``
are validated by the detector's own model when it is built, so a wrong key is named there with
the keys that detector allows. One key per built-in detector (``motion:``, ``scene_change:``,
``objects:``, ``detector_manifest:``) is shorthand for such an entry.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from openral_remote.config import ZenohConfig

DEFAULT_EVENT_LISTEN = "tcp/127.0.0.1:7448"
"""Where the event publisher listens when the file names no endpoint: this machine only."""


class DetectorConfig(BaseModel):
    """One detector: a name of the ``openral.detectors`` entry-point group and its parameters."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: str = Field(min_length=1, description="The detector (motion, scene_change, objects, or a plugin's).")
    params: dict[str, Any] = Field(
        default_factory=dict, description="The detector's own parameters, validated by its typed model."
    )


@dataclass(frozen=True)
class DetectorEntry:
    """A detector as configured, with where in the file it was configured (for errors)."""

    config: DetectorConfig
    kind_field: str
    """Where the kind is named: ``detectors[0].kind``, or a shorthand key (``motion``)."""
    params_field: str
    """Where its params are: ``detectors[0].params``, or a shorthand key."""


_SHORTHAND = ("motion", "scene_change", "objects")


class PerceptionParams(BaseModel):
    """``params`` of the ``perception`` observer (and ``backend_params.perception`` of a GStreamer camera)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    sensors: list[str] | None = Field(default=None, description="Cameras to watch (default: every camera).")
    rate_hz: float = Field(default=5.0, gt=0, le=1000, description="Detections per second per camera and kind.")
    burst: int = Field(default=1, ge=1, le=100)
    detectors: list[DetectorConfig] = Field(
        default_factory=list, description="The detectors to run, each {kind, params}; one per kind."
    )
    motion: dict[str, Any] | None = Field(default=None, description="Shorthand for {kind: motion, params: ...}.")
    scene_change: dict[str, Any] | None = Field(
        default=None, description="Shorthand for {kind: scene_change, params: ...}."
    )
    objects: dict[str, Any] | None = Field(default=None, description="Shorthand for {kind: objects, params: ...}.")
    detector_manifest: str | None = Field(
        default=None,
        description="Shorthand for {kind: objects, params: {manifest: ...}}: a kind: detector rSkill manifest.",
    )
    zenoh: ZenohConfig | None = Field(
        default=None,
        description=f"Publish events on Zenoh with this session (listening on {DEFAULT_EVENT_LISTEN} unless it says).",
    )
    robot: str | None = Field(default=None, description="Robot segment of the Zenoh keys (default: the robot id).")
    ros2: bool = Field(default=False, description="Also publish on ROS 2 /openral/perception/<kind> (needs rclpy).")

    @field_validator("zenoh")
    @classmethod
    def _loopback_unless_told(cls, zenoh: ZenohConfig | None) -> ZenohConfig | None:
        """A peer session given no endpoint to listen on would listen on every interface (Zenoh's default)."""
        if zenoh is None or zenoh.mode != "peer" or zenoh.listen:
            return zenoh
        listen = "tcp/127.0.0.1:0" if zenoh.connect else DEFAULT_EVENT_LISTEN
        return zenoh.model_copy(update={"listen": [listen]})

    def detector_entries(self) -> list[DetectorEntry]:
        """Every detector configured, the ``detectors`` list first, then the shorthand keys in their order."""
        entries = [
            DetectorEntry(config, f"detectors[{index}].kind", f"detectors[{index}].params")
            for index, config in enumerate(self.detectors)
        ]
        for key in _SHORTHAND:
            params = getattr(self, key)
            if params is not None:
                entries.append(DetectorEntry(DetectorConfig(kind=key, params=params), key, key))
        if self.detector_manifest is not None:
            config = DetectorConfig(kind="objects", params={"manifest": self.detector_manifest})
            entries.append(DetectorEntry(config, "detector_manifest", "detector_manifest"))
        return entries
