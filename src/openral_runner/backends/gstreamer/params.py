"""``backend_params`` of the ``gstreamer`` backend, validated without ``gi``.

A sensor block names either a raw ``pipeline`` or a ``source`` (plus ``device``, ``encoded``,
...) from which a :class:`PipelineSpec` is made, with size, rate, pixel format and the ROS tee
taken from the sensor's own fields. Every error names its field as
``sensors[<id>].backend_params.<key>`` (or the sensor field it came from).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from openral_core import FrameEncoding, ROSConfigError, SensorReaderConfig
from openral_core.config import config_error_from_validation
from openral_perception.params import PerceptionParams
from openral_runner.backends.gstreamer.pipeline import Codec, PipelineSpec, PixelFormat, Platform, Source
from openral_runner.sensor_reader import backend_params_field, require_video_file

FORMAT_OF_ENCODING: dict[FrameEncoding, PixelFormat] = {
    FrameEncoding.BGR8: PixelFormat.BGR,
    FrameEncoding.RGB8: PixelFormat.RGB,
    FrameEncoding.MONO8: PixelFormat.GRAY8,
}
"""Sensor ``encoding`` → raw format delivered to the appsink."""

_SPEC_FIELD_ORIGIN = {
    "width": "width",
    "height": "height",
    "fps": "fps",
    "output_format": "encoding",
    "enable_ros_tee": "publish_to_ros",
    "ros_rate_hz": "publish_rate_hz",
}
"""PipelineSpec fields filled from the sensor's own fields (named so in errors)."""


class GStreamerParams(BaseModel):
    """``backend_params`` of the ``gstreamer`` backend: a raw ``pipeline``, or a ``source`` to build one.

    fps, width, height, encoding, max_age_ms and publish_to_ros come from the sensor's own fields.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    pipeline: str | None = Field(default=None, min_length=1, description="raw gst-launch pipeline ending in appsink")
    source: Source | None = Field(default=None, description="testsrc, usb, csi, rtsp or file")
    device: str | int | None = Field(default=None, description="/dev/videoN, CSI sensor id, rtsp:// URL or file")
    encoded: Codec | None = Field(default=None, description="h264, h265 or mjpeg; none for raw video")
    pattern: str | None = Field(default=None, description="videotestsrc pattern (testsrc)")
    platform: Platform | None = Field(default=None, description="tegra, nvidia_desktop or cpu_only; detected if unset")
    enable_nvmm: bool = False
    enable_event_tee: bool = False
    event_rate_hz: float | None = Field(default=None, gt=0)
    max_buffers: int | None = Field(default=None, ge=1)
    appsink_name: str = "openral_sink"
    perception: PerceptionParams | None = Field(
        default=None, description="Event detectors on the event leg (needs enable_event_tee)."
    )

    @model_validator(mode="after")
    def _pipeline_or_source(self) -> Self:
        if (self.pipeline is None) == (self.source is None):
            raise ValueError(
                "set exactly one of pipeline (a raw GStreamer pipeline) or source (testsrc, usb, csi, rtsp, file)"
            )
        if self.pipeline is not None:
            builder_keys = sorted(
                name
                for name in self.model_fields_set
                if name not in {"pipeline", "appsink_name"} and getattr(self, name) not in (None, False)
            )
            if builder_keys:
                raise ValueError(f"{', '.join(builder_keys)} only apply to a built pipeline (source), not to pipeline")
        if self.perception is not None and not self.enable_event_tee:
            raise ValueError("perception runs on the event leg: set enable_event_tee: true")
        return self


@dataclass(frozen=True)
class ReaderSettings:
    """What a ``GStreamerSensorReader`` is constructed with: a spec or a raw pipeline, and the rest."""

    sensor_id: str
    default_max_age_ms: float
    spec: PipelineSpec | None
    pipeline: str | None
    appsink_name: str
    platform: Platform | None
    width: int | None
    height: int | None
    perception: PerceptionParams | None = None


def settings_from_config(config: SensorReaderConfig, *, base_dir: Path | None = None) -> ReaderSettings:
    """Validate a sensor block for the ``gstreamer`` backend.

    Args:
        config: The sensor's block of the deployment.
        base_dir: Directory a relative file path is resolved against; the working directory when ``None``.

    Raises:
        ROSConfigError: A wrong or missing parameter, named as ``sensors[<id>].backend_params.<key>``.
    """
    sid = config.sensor_id
    prefix = backend_params_field(config)
    params = _validate(GStreamerParams, dict(config.backend_params), prefix=prefix)
    output = FORMAT_OF_ENCODING.get(config.encoding)
    if output is None:
        raise ROSConfigError(
            f"the gstreamer backend cannot deliver {config.encoding.value}",
            field=f"sensors[{sid}].encoding",
            hint="use bgr8, rgb8 or mono8",
        )
    settings = ReaderSettings(
        sensor_id=sid,
        default_max_age_ms=config.max_age_ms,
        spec=None,
        pipeline=params.pipeline,
        appsink_name=params.appsink_name,
        platform=params.platform,
        width=config.width,
        height=config.height,
        perception=params.perception,
    )
    if params.pipeline is not None:
        if config.publish_to_ros:
            raise ROSConfigError(
                "publish_to_ros needs a pipeline the reader builds (backend_params.source), not a raw pipeline",
                field=f"sensors[{sid}].publish_to_ros",
                hint="add your own tee and ROS leg to the pipeline string, or use source",
            )
        return settings
    device = None if params.device is None else str(params.device)
    if params.source is Source.FILE and device is not None:
        device = str(require_video_file(device, base_dir, sensor_id=sid))
    data: dict[str, Any] = {
        "source": params.source,
        "device": device,
        "width": config.width,
        "height": config.height,
        "fps": config.fps,
        "encoded": params.encoded,
        "pattern": params.pattern,
        "enable_nvmm": params.enable_nvmm,
        "enable_ros_tee": config.publish_to_ros,
        "ros_rate_hz": config.publish_rate_hz,
        "enable_event_tee": params.enable_event_tee,
        "event_rate_hz": params.event_rate_hz,
        "max_buffers": params.max_buffers,
        "appsink_name": params.appsink_name,
        "output_format": output,
    }
    spec = _validate(
        PipelineSpec,
        {key: value for key, value in data.items() if value is not None},
        prefix=prefix,
        renamed={key: f"sensors[{sid}].{origin}" for key, origin in _SPEC_FIELD_ORIGIN.items()},
    )
    return ReaderSettings(**{**settings.__dict__, "spec": spec, "pipeline": None})


def refield(error: ROSConfigError, field: str) -> ROSConfigError:
    """The same error, naming ``field`` instead."""
    message = str(error)
    if error.field:
        message = message.removeprefix(f"{error.field}: ")
    if error.hint:
        message = message.removesuffix(f" ({error.hint})")
    return ROSConfigError(message, field=field, hint=error.hint)


ModelT = TypeVar("ModelT", bound=BaseModel)


def _validate(
    model: type[ModelT], data: dict[str, Any], *, prefix: str, renamed: dict[str, str] | None = None
) -> ModelT:
    """``model.model_validate(data)``; a failure names the field ``<prefix>.<key>`` (or its ``renamed`` origin)."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        error = config_error_from_validation(exc, model)
        key = error.field
        field = prefix if key is None else (renamed or {}).get(key, f"{prefix}.{key}")
        raise refield(error, field) from exc


__all__ = ["FORMAT_OF_ENCODING", "GStreamerParams", "ReaderSettings", "refield", "settings_from_config"]
