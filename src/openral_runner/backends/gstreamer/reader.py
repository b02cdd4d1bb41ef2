"""``GStreamerSensorReader``: frames from a GStreamer pipeline's appsink into a latest-frame slot.

The pipeline comes from a :class:`PipelineSpec` (built by :func:`build_pipeline_string`) or is
a raw ``gst-launch`` string; its policy leg ends in an appsink whose ``new-sample`` signal
runs :meth:`GStreamerSensorReader._on_new_sample` on the streaming thread. A callback rather
than a pull thread: the frame is published the moment the sink has it (no poll interval), and
there is no extra Python thread to wake, schedule and join.

Frames and stamps: :mod:`~openral_runner.backends.gstreamer.sample` turns each sample into a
frame (one copy, the real row stride) stamped at capture. The pipeline is forced onto a
``GstSystemClock`` of type ``MONOTONIC`` (``CLOCK_MONOTONIC``, the clock of
``time.monotonic_ns``), so that stamp is on the very clock staleness is measured with. Live
sources stamp PTS at capture (``v4l2src`` from the driver's timestamp), so decoding and
conversion are not counted as freshness.

Formats: the appsink's caps are narrowed to BGR, RGB and GRAY8 (``bgr8``, ``rgb8``, ``mono8``);
a pipeline whose upstream can only deliver something else is a ``ROSConfigError`` at ``open()``.

The event leg (``enable_event_tee``): its appsink's frames go to a :class:`FrameConsumer` (the
perception publisher, when ``backend_params.perception`` is set), started and closed with the
pipeline; the consumer only takes a reference, so the leg never waits on detectors.

Errors: a bus sync handler (called on the posting thread, so no bus thread either) latches an
ERROR as ``ROSRuntimeError`` naming the element, raised by the next read; a failure while
starting is raised by ``open()`` itself. EOS is not an error: the last frame is served until it
is older than the limit.
"""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path
from typing import Any, Protocol

import structlog

from openral_core import ROSConfigError, ROSError, ROSRuntimeError, SensorFrame, SensorReaderConfig
from openral_perception.observer import build_publisher
from openral_runner.backends.gstreamer.gst import GLib, GObject, Gst, GstApp
from openral_runner.backends.gstreamer.params import refield, settings_from_config
from openral_runner.backends.gstreamer.pipeline import (
    PipelineSpec,
    Platform,
    build_pipeline_string,
    detect_platform,
    ensure_appsink_name,
)
from openral_runner.backends.gstreamer.sample import CONVERT_HINT, SUPPORTED_FORMATS, AppsinkTap, SampleFrames
from openral_runner.frame_slot import LatestFrameSlot, SlotReader

_log = structlog.get_logger(__name__)

_SUPPORTED_CAPS = f"video/x-raw,format=(string){{{','.join(SUPPORTED_FORMATS)}}}"
_FORMAT_FIELD = re.compile(r"format=\(string\)(\{[^}]*\}|[\w]+)")
_MISSING_ELEMENT = re.compile(r'no element "([^"]+)"')
_PACKAGE_HINTS = (
    ("avdec_", "apt-get install gstreamer1.0-libav"),
    ("nv", "this NVIDIA element needs the NVIDIA GStreamer plugins (Jetson L4T or the nvcodec plugin)"),
    ("x264", "apt-get install gstreamer1.0-plugins-ugly"),
)
_NULL_STATE_TIMEOUT_NS = 5 * Gst.SECOND


class FrameConsumer(Protocol):
    """Takes the frames of the event leg's appsink; started when the pipeline starts, closed when it stops."""

    def start(self) -> None:
        """Get ready for frames (open sinks, start a worker)."""

    def submit(self, frame: SensorFrame) -> None:
        """Take one frame (on the streaming thread): keep a reference, never block."""

    def close(self) -> None:
        """Let go: the pipeline stopped."""


class GStreamerSensorReader(SlotReader):
    """Runs a GStreamer pipeline and serves the latest frame of its appsink.

    Args:
        sensor_id: Reader id.
        spec: Pipeline description (exactly one of ``spec`` and ``pipeline``).
        pipeline: Raw ``gst-launch`` string ending in an appsink (renamed to ``appsink_name``).
        platform: Platform the spec is built for; detected when ``None``.
        appsink_name: The appsink to read (raw pipelines; a spec names its own).
        default_max_age_ms: Staleness limit when ``read_latest`` is given none.
        width / height: Expected frame size; a different delivered size is a reader failure.
            Default: the spec's size.
        frame_id: Optical frame of the camera, copied into every frame.
        events: Takes the frames of the event leg (``enable_event_tee``), e.g. a perception
            publisher; started and closed with the pipeline.

    Raises:
        ROSConfigError: Both or neither of spec and pipeline; a pipeline with no appsink; CSI or
            NVMM off Tegra.
    """

    def __init__(
        self,
        *,
        sensor_id: str,
        spec: PipelineSpec | None = None,
        pipeline: str | None = None,
        platform: Platform | None = None,
        appsink_name: str | None = None,
        default_max_age_ms: float = 100.0,
        width: int | None = None,
        height: int | None = None,
        frame_id: str | None = None,
        events: FrameConsumer | None = None,
    ) -> None:
        if (spec is None) == (pipeline is None):
            raise ROSConfigError(
                f"sensor '{sensor_id}': give exactly one of spec (a PipelineSpec) or pipeline (a raw string)"
            )
        self.sensor_id = sensor_id
        self.frame_id = frame_id
        if spec is not None:
            if appsink_name not in (None, spec.appsink_name):
                raise ROSConfigError(
                    f"sensor '{sensor_id}': appsink_name '{appsink_name}' differs from the spec's "
                    f"'{spec.appsink_name}'",
                    hint="set PipelineSpec.appsink_name instead",
                )
            # An explicit platform builds its own pipeline (parsing names what this host lacks);
            # only a detected one is tailored to the elements installed here.
            probe = None if platform is not None else _has_element
            platform = platform or detect_platform(probe=_has_element)
            self.pipeline_string = build_pipeline_string(spec, platform, element_present=probe)
            self.appsink_name = spec.appsink_name
            width = spec.width if width is None else width
            height = spec.height if height is None else height
        else:
            self.appsink_name = appsink_name or "openral_sink"
            self.pipeline_string = ensure_appsink_name(str(pipeline), self.appsink_name)
        if events is not None and (spec is None or not spec.enable_event_tee):
            raise ROSConfigError(
                f"sensor '{sensor_id}': event detectors run on the event leg", hint="set enable_event_tee"
            )
        self.spec = spec
        self.width = width
        self.height = height
        self.events = events
        self._frames = SampleFrames(sensor_id, width=width, height=height, frame_id=frame_id)
        self._event_tap: AppsinkTap | None = None
        self._slot = LatestFrameSlot(sensor_id, default_max_age_ms=default_max_age_ms, clock_ns=time.monotonic_ns)
        self._clock = GObject.new(Gst.SystemClock, clock_type=Gst.ClockType.MONOTONIC)
        self._lock = threading.Lock()
        self._pipeline: Any = None
        self._sink: Any = None
        self._sample_handler: int | None = None
        self._eos = False
        self._bus_error: ROSRuntimeError | None = None

    @classmethod
    def from_config(
        cls, config: SensorReaderConfig, *, hal: Any, robot: Any, base_dir: Path | None = None
    ) -> GStreamerSensorReader:
        """Plugin constructor; ``backend_params`` are validated as :class:`~.params.GStreamerParams`.

        Args:
            config: The sensor's block of the deployment.
            hal: Unused (the camera is not part of the HAL).
            robot: Unused.
            base_dir: Directory a relative file path is resolved against (the deployment
                file's); the working directory when ``None``.

        Raises:
            ROSConfigError: A wrong or missing parameter, named as ``sensors[<id>].backend_params.<key>``.
        """
        settings = settings_from_config(config, base_dir=base_dir)
        events = None
        if settings.perception is not None:
            events = build_publisher(
                settings.perception,
                robot_id=robot.robot_id,
                base_dir=base_dir,
                field=f"sensors[{settings.sensor_id}].backend_params.perception",
            )
        try:
            reader = cls(
                sensor_id=settings.sensor_id,
                spec=settings.spec,
                pipeline=settings.pipeline,
                platform=settings.platform,
                appsink_name=None if settings.spec is not None else settings.appsink_name,
                default_max_age_ms=settings.default_max_age_ms,
                width=settings.width,
                height=settings.height,
                events=events,
            )
            reader.check()  # what parses now starts later: validate refuses a pipeline open() would
            return reader
        except ROSConfigError as exc:  # a builder error names a spec field: say where it came from
            if exc.field is not None and exc.field.startswith("sensors["):
                raise
            key = "" if exc.field is None else f".{exc.field}"
            raise refield(exc, f"sensors[{settings.sensor_id}].backend_params{key}") from exc

    # -- lifecycle -------------------------------------------------------------------------

    @property
    def eos(self) -> bool:
        """The pipeline reached end of stream (a file ended); the last frame ages out."""
        return self._eos

    def open(self) -> None:
        """Parse the pipeline, attach to its appsink and bus, and set it PLAYING. Idempotent.

        Raises:
            ROSConfigError: The pipeline does not parse, has no such appsink, or can only
                deliver a format the reader does not take.
            ROSRuntimeError: The pipeline fails to start (e.g. a missing device or file).
        """
        with self._lock:
            if self._pipeline is not None:
                return
            self._slot.open()
            self._frames.reset()
            self._eos = False
            self._bus_error = None
            try:
                self._start()
            except BaseException:
                self._stop()
                self._slot.close()
                raise
            _log.info("gstreamer sensor open", sensor_id=self.sensor_id, pipeline=self.pipeline_string)

    def close(self) -> None:
        """Stop the pipeline (state NULL) and stop serving frames. Idempotent."""
        with self._lock:
            self._slot.close()
            self._stop()

    # -- reading ---------------------------------------------------------------------------

    # -- pipeline plumbing -----------------------------------------------------------------

    def check(self) -> None:
        """Parse the pipeline and check its appsink and formats without starting it.

        No element leaves the NULL state, so no device is opened: this is what ``openral validate``
        can know about a pipeline without the camera.

        Raises:
            ROSConfigError: As :meth:`open` would for the same pipeline.
        """
        pipeline, _sink = self._parse()
        pipeline.set_state(Gst.State.NULL)

    def _parse(self) -> tuple[Any, Any]:
        """The parsed pipeline (state NULL) and its appsink, restricted to the formats the reader takes."""
        try:
            pipeline = Gst.parse_launch(self.pipeline_string)
        except GLib.Error as exc:
            raise _parse_error(self.sensor_id, self.pipeline_string, exc) from exc
        if not isinstance(pipeline, Gst.Pipeline):
            raise ROSConfigError(
                f"sensor '{self.sensor_id}': '{self.pipeline_string}' is a single element, not a pipeline",
                hint="link a source to the appsink: 'videotestsrc ! videoconvert ! appsink'",
            )
        sink = pipeline.get_by_name(self.appsink_name)
        if not isinstance(sink, GstApp.AppSink):
            found = "no element" if sink is None else f"a {type(sink).__name__}, not an appsink,"
            raise ROSConfigError(
                f"sensor '{self.sensor_id}': the pipeline has {found} named '{self.appsink_name}'",
                hint=f"end the pipeline with 'appsink name={self.appsink_name}'",
            )
        self._restrict_caps(sink)
        return pipeline, sink

    def _start(self) -> None:
        pipeline, sink = self._parse()
        self._pipeline = pipeline
        self._sink = sink
        sink.set_property("emit-signals", True)
        self._sample_handler = sink.connect("new-sample", self._on_new_sample)
        pipeline.use_clock(self._clock)
        pipeline.get_bus().set_sync_handler(self._on_bus_message)
        if self.events is not None and self.spec is not None:
            event_frames = SampleFrames(self.sensor_id, frame_id=self.frame_id)
            event_sink = pipeline.get_by_name(self.spec.event_appsink_name)
            self._event_tap = AppsinkTap(event_sink, event_frames, self.events.submit)
            self.events.start()
        if pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
            cause = self._bus_error
            detail = str(cause).removeprefix(f"sensor '{self.sensor_id}': ") if cause else self.pipeline_string
            raise ROSRuntimeError(f"sensor '{self.sensor_id}': the pipeline failed to start: {detail}")

    def _stop(self) -> None:
        pipeline, sink, handler = self._pipeline, self._sink, self._sample_handler
        self._pipeline = self._sink = self._sample_handler = None
        if pipeline is None:
            return
        pipeline.set_state(Gst.State.NULL)
        pipeline.get_state(_NULL_STATE_TIMEOUT_NS)
        if sink is not None and handler is not None:
            sink.disconnect(handler)
        if self._event_tap is not None:
            self._event_tap.detach()
            self._event_tap = None
        if self.events is not None:
            self.events.close()
        pipeline.get_bus().set_sync_handler(None)

    def _restrict_caps(self, sink: Any) -> None:
        """Let the appsink accept only formats that become frames; reject a pipeline that cannot deliver one."""
        supported = Gst.Caps.from_string(_SUPPORTED_CAPS)
        own = sink.get_property("caps")
        wanted = supported if own is None or own.is_any() else own.intersect(supported)
        if wanted.is_empty():
            raise ROSConfigError(
                f"sensor '{self.sensor_id}': appsink caps '{own.to_string()}' allow none of the formats the "
                f"reader takes ({', '.join(SUPPORTED_FORMATS)})",
                hint=CONVERT_HINT,
            )
        sink.set_property("caps", wanted)
        upstream = sink.get_static_pad("sink").peer_query_caps(None)
        if upstream is None or upstream.is_any() or upstream.is_empty() or upstream.can_intersect(wanted):
            return
        described = upstream.to_string()
        formats = sorted({f for match in _FORMAT_FIELD.findall(described) for f in match.strip("{}").split(",")})
        named = ", ".join(f.strip() for f in formats) or described
        raise ROSConfigError(
            f"sensor '{self.sensor_id}': the pipeline delivers format {named} ({described[:160]}); the reader "
            f"takes {', '.join(SUPPORTED_FORMATS)}",
            hint=CONVERT_HINT,
        )

    def _on_bus_message(self, _bus: Any, message: Any) -> Any:
        """Bus sync handler (posting thread): latch errors, note EOS; every message is dropped here."""
        kind = message.type
        if kind == Gst.MessageType.ERROR:
            error, debug = message.parse_error()
            source = message.src.get_name() if message.src is not None else "pipeline"
            text = f"sensor '{self.sensor_id}': GStreamer element '{source}' failed: {error.message}"
            if debug:
                text += f" [{' '.join(debug.split())}]"
            if debug and "not-negotiated" in debug:
                text += f" (the appsink takes {', '.join(SUPPORTED_FORMATS)}: {CONVERT_HINT})"
            self._latch(ROSRuntimeError(text))
        elif kind == Gst.MessageType.EOS:
            self._eos = True
            _log.info("gstreamer sensor reached end of stream", sensor_id=self.sensor_id)
        elif kind == Gst.MessageType.WARNING:
            warning, debug = message.parse_warning()
            _log.warning("gstreamer warning", sensor_id=self.sensor_id, message=warning.message, debug=debug)
        return Gst.BusSyncReply.DROP

    def _latch(self, error: ROSRuntimeError) -> None:
        if self._bus_error is None:
            self._bus_error = error
        self._slot.fail(error)

    def _on_new_sample(self, sink: Any) -> Any:
        """``new-sample`` handler (streaming thread): one copy out of the buffer, publish."""
        arrival_ns = time.monotonic_ns()
        try:
            sample = sink.emit("pull-sample")  # the action signal: see ``gst`` on why not ``pull_sample()``
            if sample is None:  # flushing or EOS
                return Gst.FlowReturn.OK
            frame = self._frames.frame(sample, sink, arrival_ns)
        except ROSError as exc:
            self._latch(exc if isinstance(exc, ROSRuntimeError) else ROSRuntimeError(str(exc)))
            return Gst.FlowReturn.ERROR
        except Exception as exc:
            self._latch(ROSRuntimeError(f"sensor '{self.sensor_id}': could not read a GStreamer sample: {exc}"))
            return Gst.FlowReturn.ERROR
        self._slot.publish(frame)
        return Gst.FlowReturn.OK


def _has_element(name: str) -> bool:
    """Whether this process's GStreamer registry has ``name`` (no subprocess)."""
    return Gst.ElementFactory.find(name) is not None


def _parse_error(sensor_id: str, pipeline: str, exc: Any) -> ROSConfigError:
    missing = _MISSING_ELEMENT.search(str(exc.message))
    hint = None
    if missing:
        element = missing.group(1)
        hint = next(
            (text for prefix, text in _PACKAGE_HINTS if element.startswith(prefix)),
            f"install the GStreamer plugin that provides '{element}' (check with gst-inspect-1.0 {element})",
        )
    return ROSConfigError(f"sensor '{sensor_id}': cannot parse pipeline '{pipeline}': {exc.message}", hint=hint)


__all__ = ["SUPPORTED_FORMATS", "FrameConsumer", "GStreamerSensorReader"]
