"""GStreamer pipeline strings and platform detection, in pure Python (no ``gi`` import).

:func:`build_pipeline_string` turns a :class:`PipelineSpec` into a ``gst-launch`` string whose
policy leg ends in the appsink the reader pulls from. Element choices depend on the
:class:`Platform`:

==================  ===============================  =============  ===============================
platform            H.264 / H.265 decoder            MJPEG decoder  colour conversion
==================  ===============================  =============  ===============================
``tegra``           ``nvv4l2decoder`` (NVMM output)  ``nvjpegdec``  ``nvvidconv``, ``videoconvert``
``nvidia_desktop``  ``nvh264dec`` / ``nvh265dec``    ``nvjpegdec``  ``videoconvert``
``cpu_only``        ``avdec_h264`` / ``avdec_h265``  ``jpegdec``    ``videoconvert``
==================  ===============================  =============  ===============================

An accelerated element is emitted only if the host has it (``element_present``, by default
``gst-inspect-1.0 --exists``); otherwise the stock CPU element of ``gst-plugins-base/good/bad``
or ``gst-libav`` is used and a warning says so. ``nvvideoconvert`` (DeepStream, proprietary)
is never emitted, and NVMM memory exists only on Tegra.

With ``enable_ros_tee`` / ``enable_event_tee`` the decoded stream goes through
``tee name=openral_cam_tee`` and every leg (policy included) starts with
:data:`LEAKY_BRANCH_QUEUE`, so a stalled consumer drops its own frames and never
back-pressures the policy.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from collections.abc import Callable
from enum import StrEnum
from fractions import Fraction
from functools import cache
from pathlib import Path
from typing import Final, Self

import structlog
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from openral_core import ROSConfigError

_log = structlog.get_logger(__name__)

TEE_NAME: Final[str] = "openral_cam_tee"
"""Name of the per-camera tee: the attach point for consumers of the camera stream."""

LEAKY_BRANCH_QUEUE: Final[str] = "queue leaky=downstream max-size-buffers=2"
"""Isolation policy of every tee branch: keep the two newest buffers, drop older ones."""

TEGRA_RELEASE_FILE: Final[Path] = Path("/etc/nv_tegra_release")
"""Present on Jetson (L4T) systems only."""

INSPECT_TIMEOUT_S: Final[float] = 10.0
"""``gst-inspect-1.0`` can rebuild the plugin registry on its first run; allow for it."""

_ELEMENT_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
_PATTERN = re.compile(r"^[a-z0-9\-]+$")


def leaky_branch(elements: str, *, tee_name: str = TEE_NAME) -> str:
    """One tee branch: ``<tee>. ! <leaky queue> ! <elements>``."""
    return f"{tee_name}. ! {LEAKY_BRANCH_QUEUE} ! {elements}"


class Platform(StrEnum):
    """Hardware family, which decides the decoder and converter elements."""

    TEGRA = "tegra"
    NVIDIA_DESKTOP = "nvidia_desktop"
    CPU_ONLY = "cpu_only"


class Source(StrEnum):
    """Where frames come from."""

    USB = "usb"
    CSI = "csi"
    RTSP = "rtsp"
    FILE = "file"
    TESTSRC = "testsrc"


class Codec(StrEnum):
    """Compressed stream carried by the source (``None`` in a spec means raw video)."""

    H264 = "h264"
    H265 = "h265"
    MJPEG = "mjpeg"


class PixelFormat(StrEnum):
    """GStreamer raw formats the reader turns into frames (``bgr8``, ``rgb8``, ``mono8``)."""

    BGR = "BGR"
    RGB = "RGB"
    GRAY8 = "GRAY8"


_NEEDS_DEVICE = frozenset({Source.USB, Source.RTSP, Source.FILE})
_LIVE = frozenset({Source.USB, Source.CSI, Source.RTSP, Source.TESTSRC})


class PipelineSpec(BaseModel):
    """Validated description of a GStreamer ingest pipeline.

    Attributes:
        source: Where frames come from.
        device: ``/dev/videoN`` (usb), sensor id (csi, default 0), ``rtsp://`` URL, or file path.
        width / height: Output size; ``None`` keeps the source's size (both or neither).
        fps: Frame rate requested from live sources (files play at their own rate).
        encoded: Compressed stream of the source; ``None`` is raw video (usb, testsrc), lets
            ``decodebin`` decide (file), or means H.264 (rtsp).
        pattern: ``videotestsrc`` pattern (testsrc only).
        enable_nvmm: Tegra only: keep decoded frames in NVMM memory up to each tee leg.
        enable_ros_tee: Add a BGR leg ending in ``ros_appsink_name`` for a ROS publisher.
        enable_event_tee: Add a BGR leg at ``event_rate_hz`` ending in ``event_appsink_name``.
        ros_rate_hz: Rate cap of the ROS leg; ``None`` publishes every frame.
        max_buffers: Queue length of the policy appsink (it drops older frames).
        output_format: Pixel format delivered to the policy appsink.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    source: Source
    device: str | None = None
    width: int | None = Field(default=None, ge=1)
    height: int | None = Field(default=None, ge=1)
    fps: float = Field(default=30.0, gt=0, le=1000)
    encoded: Codec | None = None
    pattern: str = "smpte"
    enable_nvmm: bool = False
    enable_ros_tee: bool = False
    enable_event_tee: bool = False
    appsink_name: str = "openral_sink"
    ros_appsink_name: str = "ros_sink"
    event_appsink_name: str = "event_sink"
    ros_rate_hz: float | None = Field(default=None, gt=0)
    event_rate_hz: float = Field(default=5.0, gt=0, le=1000)
    max_buffers: int = Field(default=1, ge=1, le=64)
    output_format: PixelFormat = PixelFormat.BGR

    @field_validator("appsink_name", "ros_appsink_name", "event_appsink_name")
    @classmethod
    def _element_name(cls, value: str) -> str:
        if not _ELEMENT_NAME.match(value):
            raise ValueError(
                f"{value!r} is not a valid GStreamer element name: use letters, digits, '_' or '-', "
                "starting with a letter or '_'"
            )
        return value

    @field_validator("pattern")
    @classmethod
    def _pattern(cls, value: str) -> str:
        if not _PATTERN.match(value):
            raise ValueError(f"{value!r} is not a videotestsrc pattern name (e.g. smpte, ball, solid-color)")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if self.source in _NEEDS_DEVICE and not self.device:
            what = {Source.USB: "a device node like /dev/video0", Source.RTSP: "an rtsp:// URL"}
            raise ValueError(f"source {self.source.value} needs device: {what.get(self.source, 'a video file path')}")
        if self.source is Source.CSI and self.device is not None and not self.device.isdigit():
            raise ValueError(f"source csi takes a numeric sensor id as device, not '{self.device}'")
        if self.source is Source.TESTSRC and self.device is not None:
            raise ValueError("source testsrc takes no device")
        if self.source in (Source.TESTSRC, Source.CSI) and self.encoded is not None:
            raise ValueError(f"source {self.source.value} delivers raw video: remove encoded")
        if (self.width is None) != (self.height is None):
            raise ValueError("set both width and height, or neither")
        names = [self.appsink_name]
        if self.enable_ros_tee:
            names.append(self.ros_appsink_name)
        if self.enable_event_tee:
            names.append(self.event_appsink_name)
        if len(set(names)) != len(names) or TEE_NAME in names:
            raise ValueError(f"appsink names must differ from each other and from '{TEE_NAME}': {names}")
        return self

    @property
    def is_live(self) -> bool:
        """True for cameras and streams; false for files (which play at their own rate)."""
        return self.source in _LIVE


# -- host probing -----------------------------------------------------------------------------


@cache
def inspect_element_present(element_name: str, *, timeout_s: float = INSPECT_TIMEOUT_S) -> bool:
    """Whether the host's GStreamer has ``element_name`` (``gst-inspect-1.0 --exists``), cached.

    Returns ``False`` when ``gst-inspect-1.0`` is not installed or does not answer in time.
    """
    tool = shutil.which("gst-inspect-1.0")
    if tool is None:
        return False
    try:
        proc = subprocess.run([tool, "--exists", element_name], capture_output=True, timeout=timeout_s, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0


@cache
def detect_platform(
    tegra_release: Path = TEGRA_RELEASE_FILE,
    probe: Callable[[str], bool] = inspect_element_present,
) -> Platform:
    """The host's platform, cached: Tegra if ``tegra_release`` exists, NVIDIA desktop if
    ``nvh264dec`` is installed, else CPU only."""
    if tegra_release.exists():
        return Platform.TEGRA
    if probe("nvh264dec"):
        return Platform.NVIDIA_DESKTOP
    return Platform.CPU_ONLY


def nvmm_convert_element(probe: Callable[[str], bool] = inspect_element_present) -> str | None:
    """The host's NVMM colour converter: ``nvvideoconvert``, else ``nvvidconv``, else ``None``."""
    for name in ("nvvideoconvert", "nvvidconv"):
        if probe(name):
            return name
    return None


# -- appsink naming ---------------------------------------------------------------------------

_TOKEN = re.compile(r'(?:"(?:\\.|[^"\\])*"|[^\s!"])+|!')
_PROPERTY = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]*=")


def ensure_appsink_name(pipeline: str, name: str) -> str:
    """``pipeline`` with its trailing (last) ``appsink`` named ``name``.

    Unchanged when some appsink already carries ``name=<name>``; an existing ``name=`` of the
    last appsink is replaced, otherwise ``name=<name>`` is appended to its properties.

    Raises:
        ROSConfigError: ``name`` is not a valid element name, or the pipeline has no appsink.
    """
    if not _ELEMENT_NAME.match(name):
        raise ROSConfigError(f"{name!r} is not a valid GStreamer element name", field="appsink_name")
    tokens = list(_TOKEN.finditer(pipeline))
    sinks: list[tuple[int, list[re.Match[str]]]] = []
    for index, token in enumerate(tokens):
        if token.group() != "appsink":
            continue
        props: list[re.Match[str]] = []
        for follower in tokens[index + 1 :]:
            if not _PROPERTY.match(follower.group()):
                break
            props.append(follower)
        sinks.append((index, props))
    if not sinks:
        raise ROSConfigError(
            "the pipeline has no appsink for the reader to pull frames from",
            field="pipeline",
            hint=f"end it with '! videoconvert ! video/x-raw,format=BGR ! appsink name={name}'",
        )
    for _, props in sinks:
        if any(_property_value(p.group(), "name") == name for p in props):
            return pipeline
    index, props = sinks[-1]
    for prop in props:
        if _property_value(prop.group(), "name") is not None:
            return f"{pipeline[: prop.start()]}name={name}{pipeline[prop.end() :]}"
    end = props[-1].end() if props else tokens[index].end()
    return f"{pipeline[:end]} name={name}{pipeline[end:]}"


def _property_value(token: str, key: str) -> str | None:
    prefix = f"{key}="
    if not token.startswith(prefix):
        return None
    return token[len(prefix) :].strip('"')


# -- the builder ------------------------------------------------------------------------------

_ACCELERATED_DECODERS: dict[tuple[Platform, Codec], tuple[str, ...]] = {
    (Platform.TEGRA, Codec.H264): ("nvv4l2decoder",),
    (Platform.TEGRA, Codec.H265): ("nvv4l2decoder",),
    (Platform.TEGRA, Codec.MJPEG): ("nvjpegdec",),
    (Platform.NVIDIA_DESKTOP, Codec.H264): ("nvh264dec",),
    (Platform.NVIDIA_DESKTOP, Codec.H265): ("nvh265dec",),
    (Platform.NVIDIA_DESKTOP, Codec.MJPEG): ("nvjpegdec",),
}
_CPU_DECODERS: dict[Codec, str] = {Codec.H264: "avdec_h264", Codec.H265: "avdec_h265", Codec.MJPEG: "jpegdec"}
_NVMM_OUTPUT = frozenset({"nvv4l2decoder"})
"""Decoders whose output is ``video/x-raw(memory:NVMM)``."""
_PARSERS: dict[Codec, str | None] = {Codec.H264: "h264parse", Codec.H265: "h265parse", Codec.MJPEG: None}
_DEPAYLOADERS: dict[Codec, str] = {Codec.H264: "rtph264depay", Codec.H265: "rtph265depay", Codec.MJPEG: "rtpjpegdepay"}
_ENCODED_CAPS: dict[Codec, str] = {Codec.H264: "video/x-h264", Codec.H265: "video/x-h265", Codec.MJPEG: "image/jpeg"}
_DEMUXERS: dict[str, str] = {
    ".mp4": "qtdemux",
    ".mov": "qtdemux",
    ".m4v": "qtdemux",
    ".mkv": "matroskademux",
    ".webm": "matroskademux",
    ".avi": "avidemux",
}
_TEGRA_CONVERTERS = ("nvvidconv", "nvvideoconvert")


class _Head:
    """The source and decode part of a pipeline, and the memory its output lives in."""

    def __init__(self, elements: list[str], *, nvmm: bool, sized: bool) -> None:
        self.elements = elements
        self.nvmm = nvmm
        self.sized = sized


def build_pipeline_string(
    spec: PipelineSpec,
    platform: Platform | None = None,
    *,
    element_present: Callable[[str], bool] | None = None,
) -> str:
    """The ``gst-launch`` string for ``spec`` on ``platform`` (this host's, detected, when ``None``).

    An explicit ``platform`` builds that platform's pipeline whatever this host has (a Jetson
    pipeline can be written on a laptop): its accelerated elements are assumed present unless
    ``element_present`` says otherwise, and one the running host lacks is named by GStreamer
    when the pipeline is parsed. Only for ``platform=None`` is this host probed.

    Args:
        spec: What to capture and how to deliver it.
        platform: Decides decoder and converter; :func:`detect_platform` when ``None``.
        element_present: Probe for optional accelerated elements; by default
            :func:`inspect_element_present` on a detected platform, every element on an explicit one.

    Raises:
        ROSConfigError: CSI or NVMM requested off Tegra, or a required Jetson element is missing.
    """
    if platform is None:
        platform = detect_platform()
        present = inspect_element_present if element_present is None else element_present
    else:
        platform = Platform(platform)
        present = _assume_present if element_present is None else element_present
    if platform is not Platform.TEGRA and (spec.source is Source.CSI or spec.enable_nvmm):
        what = "source csi (nvarguscamerasrc)" if spec.source is Source.CSI else "enable_nvmm"
        raise ROSConfigError(
            f"{what} needs a Jetson (Tegra) platform, this one is {platform.value}",
            field="source" if spec.source is Source.CSI else "enable_nvmm",
            hint="use source usb/rtsp/file, or remove enable_nvmm; NVIDIA desktop GPUs still decode with nvcodec",
        )
    head = _build_head(spec, platform, present)
    nvmm_legs = head.nvmm and spec.enable_nvmm
    if head.nvmm and not nvmm_legs:
        head.elements.append(_lift_nvmm(spec, present))  # one lift (and scale) for every leg
    elif not head.nvmm and not head.sized and spec.width is not None:
        head.elements += ["videoscale", f"video/x-raw,width={spec.width},height={spec.height}"]
    lift = _lift_nvmm(spec, present) if nvmm_legs else None
    policy = _policy_leg(spec, lift)
    chain = " ! ".join(head.elements)
    if not (spec.enable_ros_tee or spec.enable_event_tee):
        return f"{chain} ! {policy}"
    legs = [leaky_branch(policy)]
    if spec.enable_ros_tee:
        legs.append(leaky_branch(_build_ros_tee_branch(spec, lift)))
    if spec.enable_event_tee:
        legs.append(leaky_branch(_build_event_tee_branch(spec, lift)))
    return f"{chain} ! tee name={TEE_NAME}  " + "  ".join(legs)


def _build_head(spec: PipelineSpec, platform: Platform, present: Callable[[str], bool]) -> _Head:
    size = _size_fields(spec)
    rate = f"framerate={_fraction(spec.fps)}"
    match spec.source:
        case Source.TESTSRC:
            caps = ",".join(["video/x-raw", *size, rate])
            return _Head([f"videotestsrc is-live=true pattern={spec.pattern}", caps], nvmm=False, sized=True)
        case Source.CSI:
            camera = _require(("nvarguscamerasrc",), present, "source csi")
            caps = ",".join(["video/x-raw(memory:NVMM)", *size, rate])
            return _Head([f"{camera} sensor-id={spec.device or 0}", caps], nvmm=True, sized=True)
        case Source.USB:
            src = f"v4l2src device={_quote(spec.device)}"
            if spec.encoded is None:
                return _Head([src, ",".join(["video/x-raw", *size, rate])], nvmm=False, sized=True)
            decode, nvmm = _decode(spec.encoded, platform, present)
            caps = ",".join([_ENCODED_CAPS[spec.encoded], *size, rate])
            return _Head([src, caps, *decode], nvmm=nvmm, sized=True)
        case Source.RTSP:
            codec = spec.encoded or Codec.H264
            decode, nvmm = _decode(codec, platform, present)
            src = f"rtspsrc location={_quote(spec.device)} latency=0"
            return _Head([src, _DEPAYLOADERS[codec], *decode], nvmm=nvmm, sized=False)
        case Source.FILE:
            src = f"filesrc location={_quote(spec.device)}"
            if spec.encoded is None:
                # On Jetson decodebin may pick nvv4l2decoder (NVMM out); nvvidconv takes either memory.
                nvmm = platform is Platform.TEGRA and any(present(name) for name in _TEGRA_CONVERTERS)
                return _Head([src, "decodebin"], nvmm=nvmm, sized=False)
            demuxer = _DEMUXERS.get(Path(str(spec.device)).suffix.lower(), "parsebin")
            decode, nvmm = _decode(spec.encoded, platform, present)
            return _Head([src, demuxer, *decode], nvmm=nvmm, sized=False)
    raise AssertionError(f"unhandled source {spec.source}")  # pragma: no cover


def _decode(codec: Codec, platform: Platform, present: Callable[[str], bool]) -> tuple[list[str], bool]:
    """Parser (if any) and decoder for ``codec``; the flag says whether output is in NVMM."""
    decoder = _CPU_DECODERS[codec]
    for candidate in _ACCELERATED_DECODERS.get((platform, codec), ()):
        if present(candidate):
            decoder = candidate
            break
    else:
        if platform is not Platform.CPU_ONLY:
            _log.warning(
                "accelerated decoder not installed; decoding on the CPU",
                platform=platform.value,
                codec=codec.value,
                wanted=list(_ACCELERATED_DECODERS.get((platform, codec), ())),
                using=decoder,
            )
    parser = _PARSERS[codec]
    return ([parser] if parser else []) + [decoder], decoder in _NVMM_OUTPUT


def _lift_nvmm(spec: PipelineSpec, present: Callable[[str], bool]) -> str:
    """Tegra: convert NVMM frames to system-memory BGRx (scaling on the VIC if a size is set)."""
    converter = _require(_TEGRA_CONVERTERS, present, "NVMM frames")
    caps = ",".join(["video/x-raw", "format=BGRx", *_size_fields(spec)])
    return f"{converter} ! {caps}"


def _policy_leg(spec: PipelineSpec, lift: str | None) -> str:
    convert = f"videoconvert ! video/x-raw,format={spec.output_format.value}"
    sink = (
        f"appsink name={spec.appsink_name} drop=true max-buffers={spec.max_buffers} "
        f"sync={_bool(not spec.is_live)} emit-signals=true enable-last-sample=false"
    )
    return " ! ".join(part for part in (lift, convert, sink) if part)


def _build_ros_tee_branch(spec: PipelineSpec, lift: str | None) -> str:
    """The observability leg: system-memory BGR, rate-capped if asked, into ``ros_appsink_name``."""
    return _side_leg(lift, spec.ros_rate_hz, spec.ros_appsink_name)


def _build_event_tee_branch(spec: PipelineSpec, lift: str | None) -> str:
    """The event leg: system-memory BGR at ``event_rate_hz`` into ``event_appsink_name``."""
    return _side_leg(lift, spec.event_rate_hz, spec.event_appsink_name)


def _side_leg(lift: str | None, rate_hz: float | None, sink_name: str) -> str:
    rate = f"videorate drop-only=true ! video/x-raw,framerate={_fraction(rate_hz)}" if rate_hz else None
    convert = "videoconvert ! video/x-raw,format=BGR"
    sink = f"appsink name={sink_name} drop=true max-buffers=1 sync=false async=false"
    return " ! ".join(part for part in (lift, rate, convert, sink) if part)


def _assume_present(_element: str) -> bool:
    """An explicit platform has its elements: the first preference is built."""
    return True


def _require(candidates: tuple[str, ...], present: Callable[[str], bool], needed_for: str) -> str:
    for name in candidates:
        if present(name):
            return name
    raise ROSConfigError(
        f"{needed_for} needs the GStreamer element {' or '.join(candidates)}, which is not installed",
        hint="install NVIDIA's L4T GStreamer plugins (nvidia-l4t-gstreamer) on the Jetson",
    )


def _size_fields(spec: PipelineSpec) -> list[str]:
    return [] if spec.width is None else [f"width={spec.width}", f"height={spec.height}"]


def _fraction(rate: float) -> str:
    value = Fraction(rate).limit_denominator(1001)
    return f"{value.numerator}/{value.denominator}"


def _bool(value: bool) -> str:
    return "true" if value else "false"


def _quote(value: str | None) -> str:
    text = str(value).replace("\\", "\\\\").replace('"', '\\"')
    return f'"{text}"'


__all__ = [
    "INSPECT_TIMEOUT_S",
    "LEAKY_BRANCH_QUEUE",
    "TEE_NAME",
    "Codec",
    "PipelineSpec",
    "PixelFormat",
    "Platform",
    "Source",
    "build_pipeline_string",
    "detect_platform",
    "ensure_appsink_name",
    "inspect_element_present",
    "leaky_branch",
    "nvmm_convert_element",
]
