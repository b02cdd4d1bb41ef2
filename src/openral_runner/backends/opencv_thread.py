"""``OpenCVThreadSensorReader``: one capture thread per camera over ``cv2.VideoCapture``.

The source is a device index (``0``), a device node (``/dev/video0``), a stream URL
(``rtsp://…``) or a video file. A file can be *paced* (frames released on an absolute
schedule at the requested fps, so it behaves like a live camera) and *looped*.

Capture stamps: the thread calls ``grab()`` (which waits for and takes the next frame),
reads ``clock_ns()`` as soon as it returns, then ``retrieve()``s (decodes) the pixels. The
stamp therefore excludes decoding and colour conversion, and staleness is measured from it.

Frames are not copied: ``retrieve()`` allocates a fresh array for every frame, and that
array becomes ``SensorFrame.data`` as is (a frame already served is never overwritten).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import (
    FrameEncoding,
    ROSConfigError,
    ROSDependencyMissing,
    ROSHardwareError,
    ROSRuntimeError,
    SensorReaderConfig,
)
from openral_core.config import validate_model
from openral_core.config_files import is_regular_file
from openral_runner.frame_slot import LatestFrameSlot, SlotReader, frame_from_array
from openral_runner.sensor_reader import is_file_path, require_video_file, validate_backend_params

try:
    import cv2
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ROSDependencyMissing("cv2", extra="opencv", needed_for="the opencv_thread sensor backend") from exc

_log = structlog.get_logger(__name__)

ApiPreference = Literal["any", "v4l2", "ffmpeg", "gstreamer"]

_API_CONSTANTS: dict[str, int] = {
    "any": cv2.CAP_ANY,
    "v4l2": cv2.CAP_V4L2,
    "ffmpeg": cv2.CAP_FFMPEG,
    "gstreamer": cv2.CAP_GSTREAMER,
}

_CONVERSIONS: dict[tuple[int, FrameEncoding], int | None] = {
    (3, FrameEncoding.BGR8): None,
    (3, FrameEncoding.RGB8): cv2.COLOR_BGR2RGB,
    (3, FrameEncoding.MONO8): cv2.COLOR_BGR2GRAY,
    (2, FrameEncoding.BGR8): cv2.COLOR_GRAY2BGR,
    (2, FrameEncoding.RGB8): cv2.COLOR_GRAY2RGB,
    (2, FrameEncoding.MONO8): None,
}
"""(ndim of the captured array, wanted encoding) → ``cv2.cvtColor`` code (``None``: as captured)."""

FPS_SHORTFALL = 0.10
"""A delivered rate more than this fraction below the requested fps is logged as a warning."""

FPS_CHECK_S = 1.0
"""The delivered rate is measured over at least this long after ``open()``..."""

FPS_CHECK_FRAMES = 10
"""...and over at least this many frame periods at the requested fps."""

JOIN_TIMEOUT_S = 2.0
"""How long ``close()`` waits for the capture thread."""


class OpenCVThreadParams(BaseModel):
    """``backend_params`` of the ``opencv_thread`` backend: the one place each of its options is named and defaulted.

    fps (set on live devices; the pacing rate of paced files), width and height (open fails if the
    source delivers another size), encoding (``bgr8``, OpenCV's order, ``rgb8`` or ``mono8``) and
    max_age_ms come from the sensor's own fields (:class:`~openral_core.SensorReaderConfig`).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    device: int | str = Field(description="device index, device node, stream URL or video file path")
    loop: bool = Field(default=False, description="video files: start again at the end")
    paced: bool | None = Field(
        default=None,
        description="video files: release frame k at t0 + k / fps (late frames skip slots, never burst); unpaced "
        "files are read as fast as they decode (default true for files)",
    )
    api_preference: ApiPreference = Field(default="any", description="OpenCV capture API")
    fourcc: str | None = Field(default=None, min_length=4, max_length=4, description="pixel format, e.g. MJPG")
    buffer_size: int | None = Field(
        default=None, ge=1, description="driver frame queue length (CAP_PROP_BUFFERSIZE); 1 keeps the frame freshest"
    )
    max_read_failures: int = Field(default=10, ge=1, description="live sources: failed reads in a row before failing")


class OpenCVThreadSensorReader(SlotReader):
    """Captures one camera or video on a background thread; serves its latest frame.

    Built from the sensor's block and its validated ``backend_params``, whole::

        OpenCVThreadSensorReader(config, params)

    or in the specification's keyword form, ``OpenCVThreadSensorReader(*, sensor_id, device, fps=30,
    width=None, height=None, encoding=BGR8, default_max_age_ms=100)``, where any further keyword is
    one of :class:`OpenCVThreadParams` (``loop=True``). Both are validated by the same two models.

    Attributes:
        config: The sensor's fields (fps, size, encoding, staleness limit).
        params: The backend's options.
        device: The source as opened: a device index, or a node, URL or file path.
        is_file: Whether the source is a video file.
        paced: Whether frames are released at ``config.fps`` (``params.paced``, default true for files).

    Raises:
        ROSConfigError: A wrong or missing option (named), an encoding other than bgr8/rgb8/mono8,
            or loop/paced for a live source.
    """

    @overload
    def __init__(
        self, config: SensorReaderConfig, params: OpenCVThreadParams, *, clock_ns: Callable[[], int] = ...
    ) -> None: ...

    @overload
    def __init__(
        self,
        *,
        sensor_id: str,
        device: int | str | Path,
        fps: float = ...,
        width: int | None = ...,
        height: int | None = ...,
        encoding: FrameEncoding = ...,
        default_max_age_ms: float = ...,
        clock_ns: Callable[[], int] = ...,
        **params: Any,
    ) -> None: ...

    def __init__(
        self,
        config: SensorReaderConfig | None = None,
        params: OpenCVThreadParams | None = None,
        *,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        **keywords: Any,
    ) -> None:
        if config is None or params is None:
            config, params = _models_from_keywords(keywords)
        sensor_id = config.sensor_id
        if config.encoding not in {FrameEncoding.BGR8, FrameEncoding.RGB8, FrameEncoding.MONO8}:
            raise ROSConfigError(
                f"sensor '{sensor_id}': the opencv_thread backend cannot deliver {config.encoding}",
                hint="use encoding bgr8, rgb8 or mono8",
            )
        device = params.device
        if isinstance(device, str) and device.isdigit():
            device = int(device)
        self.is_file = isinstance(device, str) and is_file_path(device)
        if not self.is_file and (params.loop or params.paced):
            raise ROSConfigError(
                f"sensor '{sensor_id}': loop and paced apply to video files only, not to {device!r}",
                hint="remove loop/paced from backend_params",
            )
        self.config = config
        self.params = params
        self.sensor_id = sensor_id
        self.device: int | str = device
        self.paced = self.is_file if params.paced is None else params.paced
        self._clock_ns = clock_ns
        self._slot = LatestFrameSlot(sensor_id, default_max_age_ms=config.max_age_ms, clock_ns=clock_ns)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._dropped = 0
        self._read_failures = 0
        self._loops = 0
        self._eos = False
        self._size: tuple[int, int] | None = None
        self._file_fps: float | None = None
        self._measured_fps: float | None = None

    @classmethod
    def from_config(
        cls, config: SensorReaderConfig, *, hal: Any, robot: Any, base_dir: Path | None = None
    ) -> OpenCVThreadSensorReader:
        """Plugin constructor; ``backend_params`` are validated as :class:`OpenCVThreadParams`.

        Args:
            config: The sensor's block of the deployment.
            hal: Unused (the camera is not part of the HAL).
            robot: Unused.
            base_dir: Directory a relative video file path is resolved against (the
                deployment file's); the working directory when ``None``.

        Raises:
            ROSConfigError: A wrong or missing parameter; the message names it and the allowed keys.
        """
        params = validate_backend_params(OpenCVThreadParams, config, backend="opencv_thread")
        if isinstance(params.device, str) and is_file_path(params.device):
            path = require_video_file(params.device, base_dir, sensor_id=config.sensor_id)
            params = params.model_copy(update={"device": str(path)})
        return cls(config, params)

    # -- lifecycle -----------------------------------------------------------------------

    def open(self) -> None:
        """Open the source, read one frame to learn its real size, and start the capture thread.

        Idempotent. The delivered rate is measured in the background over the first second.

        Raises:
            ROSConfigError: The video file does not exist or cannot be decoded, the source
                delivers another size than requested, or the API is not in this OpenCV build.
            ROSHardwareError: The device or stream cannot be opened or delivers no frame.
        """
        if self.is_open:
            return
        cap = self._open_capture()
        try:
            self._configure(cap)
            first = self._first_frame(cap)
        except BaseException:
            cap.release()
            raise
        self._seq = 0
        self._dropped = 0
        self._read_failures = 0
        self._loops = 0
        self._eos = False
        self._measured_fps = None
        self._stop = threading.Event()  # a fresh one: a thread stuck from a previous run keeps its own
        self._slot.open()
        stamp_ns, pixels = first
        self._publish(stamp_ns, pixels)
        self._thread = threading.Thread(
            target=self._run, args=(cap, stamp_ns, self._stop), name=f"openral-opencv-{self.sensor_id}", daemon=True
        )
        self._thread.start()
        _log.info("opencv camera opened", sensor=self.sensor_id, device=str(self.device), size=self._size)

    def close(self) -> None:
        """Stop and join the capture thread, release the source. Idempotent.

        If the thread does not stop within ``JOIN_TIMEOUT_S`` (a driver stuck in a read), it
        releases the device itself when that read returns.
        """
        thread, self._thread = self._thread, None
        self._stop_worker(self._stop, thread, timeout_s=JOIN_TIMEOUT_S)

    # -- reading -------------------------------------------------------------------------

    def report(self) -> dict[str, Any]:
        """Requested versus delivered: rate, size, frames captured, slots dropped, read failures."""
        width, height = self._size or (None, None)
        return {
            "sensor_id": self.sensor_id,
            "device": str(self.device),
            "source": "file" if self.is_file else "live",
            "requested_fps": self.config.fps,
            "delivered_fps": round(self.delivered_fps, 2),
            "measured_fps": None if self._measured_fps is None else round(self._measured_fps, 2),
            "file_fps": self._file_fps,
            "requested_size": (self.config.width, self.config.height),
            "width": width,
            "height": height,
            "encoding": self.config.encoding.value,
            "frames": self._slot.frames_published,
            "dropped": self._dropped,
            "read_failures": self._read_failures,
            "loops": self._loops,
            "end_of_stream": self._eos,
        }

    # -- opening -------------------------------------------------------------------------

    def _open_capture(self) -> Any:
        """A new, opened ``cv2.VideoCapture`` on the source (overridden in tests)."""
        api = _API_CONSTANTS[self.params.api_preference]
        if api != cv2.CAP_ANY and not cv2.videoio_registry.hasBackend(api):
            hint = (
                "use the gstreamer sensor backend"
                if self.params.api_preference == "gstreamer"
                else "use api_preference: any"
            )
            raise ROSConfigError(
                f"sensor '{self.sensor_id}': this OpenCV build has no {self.params.api_preference} capture API",
                hint=hint,
            )
        if self.is_file and not is_regular_file(Path(str(self.device))):
            raise ROSConfigError(
                f"sensor '{self.sensor_id}': video file not found: {self.device}",
                hint="check backend_params.device (relative paths are resolved against the deployment file)",
            )
        cv2.setNumThreads(1)
        try:
            cap = cv2.VideoCapture(self.device, api)
        except cv2.error as exc:
            raise ROSHardwareError(f"sensor '{self.sensor_id}': cannot open {self.device!r}: {exc}") from exc
        if cap.isOpened():
            return cap
        cap.release()
        if self.is_file:
            raise ROSConfigError(
                f"sensor '{self.sensor_id}': OpenCV cannot decode video file {self.device}",
                hint="use a format the ffmpeg in opencv-python-headless reads (mp4, avi, mkv)",
            )
        raise ROSHardwareError(
            f"sensor '{self.sensor_id}': cannot open camera {self.device!r}: "
            "check it is connected, not in use by another process, and readable by this user"
        )

    def _configure(self, cap: Any) -> None:
        """Apply the requested pixel format, size, rate and buffer length (live sources)."""
        if self.is_file:
            self._file_fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
            return
        if self.params.fourcc is not None:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.params.fourcc))
        if self.config.width is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.config.width)
        if self.config.height is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.config.height)
        cap.set(cv2.CAP_PROP_FPS, self.config.fps)
        if self.params.buffer_size is not None:
            cap.set(cv2.CAP_PROP_BUFFERSIZE, self.params.buffer_size)

    def _first_frame(self, cap: Any) -> tuple[int, np.ndarray]:
        """Read one frame synchronously; check the delivered size against the requested one."""
        captured = self._capture(cap)
        if captured is None:
            if self.is_file:
                raise ROSConfigError(f"sensor '{self.sensor_id}': video file {self.device} holds no frame")
            raise ROSHardwareError(f"sensor '{self.sensor_id}': camera {self.device!r} opened but delivered no frame")
        height, width = captured[1].shape[:2]
        wanted = (self.config.width or width, self.config.height or height)
        if wanted != (width, height):
            what = "the video file is" if self.is_file else "the device delivers"
            raise ROSConfigError(
                f"sensor '{self.sensor_id}': requested {wanted[0]}x{wanted[1]} from {self.device!r}, "
                f"but {what} {width}x{height}",
                hint=f"set width: {width} and height: {height}, or leave them unset",
            )
        self._size = (width, height)
        return captured

    # -- capture thread ------------------------------------------------------------------

    def _capture(self, cap: Any) -> tuple[int, np.ndarray] | None:
        """Grab, stamp, retrieve and convert one frame; ``None`` when the source gave none."""
        if not cap.grab():
            return None
        stamp_ns = self._clock_ns()
        ok, pixels = cap.retrieve()
        if not ok or pixels is None:
            return None
        code = _CONVERSIONS.get((pixels.ndim, self.config.encoding))
        if code is not None:
            pixels = cv2.cvtColor(pixels, code)
        return stamp_ns, pixels

    def _publish(self, stamp_ns: int, pixels: np.ndarray) -> None:
        self._slot.publish(
            frame_from_array(self.sensor_id, pixels, stamp_ns=stamp_ns, seq=self._seq, encoding=self.config.encoding)
        )
        self._seq += 1

    def _run(self, cap: Any, t0_ns: int, stop: threading.Event) -> None:
        """Capture until stopped, at the end of a non-looping file, or until a failure is latched."""
        period_ns = round(1e9 / self.config.fps)
        due_ns = t0_ns + period_ns
        check_at_ns = t0_ns + round(max(FPS_CHECK_S, FPS_CHECK_FRAMES / self.config.fps) * 1e9)
        failures = 0
        try:
            while not stop.is_set():
                if self.paced:
                    due_ns = self._wait_for_slot(due_ns, period_ns, stop)
                    if stop.is_set():
                        break
                captured = self._capture(cap)
                if captured is None and self.is_file and self.params.loop:
                    cap = self._rewind(cap)
                    captured = self._capture(cap)
                    if captured is None:
                        raise ROSRuntimeError(f"sensor '{self.sensor_id}': no frame after rewinding {self.device}")
                if captured is None:
                    if self.is_file:
                        self._eos = True
                        _log.info("end of video file; serving the last frame until it is stale", sensor=self.sensor_id)
                        return
                    failures += 1
                    self._read_failures += 1
                    if failures >= self.params.max_read_failures:
                        raise ROSRuntimeError(
                            f"sensor '{self.sensor_id}': camera {self.device!r} delivered no frame in "
                            f"{failures} reads in a row: check the cable and the device"
                        )
                    stop.wait(period_ns / 1e9)
                    continue
                failures = 0
                if not self.is_file:
                    self._count_gap(captured[0], period_ns)
                self._publish(*captured)
                if check_at_ns and captured[0] >= check_at_ns and (self.paced or not self.is_file):
                    self._check_rate(self._seq - 1, captured[0] - t0_ns)
                    check_at_ns = 0
        except ROSRuntimeError as exc:
            self._slot.fail(exc)
        except Exception as exc:
            error = ROSRuntimeError(f"sensor '{self.sensor_id}': capture from {self.device!r} failed: {exc}")
            error.__cause__ = exc
            self._slot.fail(error)
        finally:
            cap.release()

    def _wait_for_slot(self, due_ns: int, period_ns: int, stop: threading.Event) -> int:
        """Sleep until the frame slot at ``due_ns``; when late, skip (and count) the slots missed.

        Returns:
            The slot after the one being captured (never a catch-up burst).
        """
        now_ns = self._clock_ns()
        if now_ns < due_ns:
            stop.wait((due_ns - now_ns) / 1e9)
        else:
            missed = (now_ns - due_ns) // period_ns
            self._dropped += missed
            due_ns += missed * period_ns
        return due_ns + period_ns

    def _rewind(self, cap: Any) -> Any:
        """Seek a looping file back to its first frame (reopening it if seeking fails)."""
        self._loops += 1
        if cap.set(cv2.CAP_PROP_POS_FRAMES, 0):
            return cap
        cap.release()
        return self._open_capture()

    def _count_gap(self, stamp_ns: int, period_ns: int) -> None:
        """Count frames a live source dropped, from gaps of 1.5 periods or more between stamps."""
        latest = self._slot.peek()
        if latest is not None:
            gap = stamp_ns - latest.stamp_ns
            if gap >= 1.5 * period_ns:
                self._dropped += round(gap / period_ns) - 1

    def _check_rate(self, intervals: int, elapsed_ns: int) -> None:
        """Log once whether the source delivers the requested rate."""
        measured = intervals * 1e9 / elapsed_ns if elapsed_ns > 0 else 0.0
        self._measured_fps = measured
        if measured < (1.0 - FPS_SHORTFALL) * self.config.fps:
            _log.warning(
                "camera delivers fewer frames than requested",
                sensor=self.sensor_id,
                device=str(self.device),
                requested_fps=self.config.fps,
                delivered_fps=round(measured, 1),
                hint="lower fps, request fourcc MJPG or a smaller size, or check USB bandwidth and exposure",
            )
        else:
            _log.info(
                "camera rate measured", sensor=self.sensor_id, requested_fps=self.config.fps, delivered_fps=measured
            )


def _models_from_keywords(keywords: dict[str, Any]) -> tuple[SensorReaderConfig, OpenCVThreadParams]:
    """The specification's keyword form as the two models a deployment gives: sensor fields, then the rest."""
    options = dict(keywords)
    if "default_max_age_ms" in options:
        options["max_age_ms"] = options.pop("default_max_age_ms")
    if isinstance(options.get("device"), Path):
        options["device"] = str(options["device"])
    sensor = {name: options.pop(name) for name in _SENSOR_FIELDS if name in options}
    config = validate_model(
        SensorReaderConfig, {**sensor, "backend": "opencv_thread"}, source="OpenCVThreadSensorReader"
    )
    params = validate_model(OpenCVThreadParams, options, source=f"sensor '{config.sensor_id}'")
    return config, params


_SENSOR_FIELDS = ("sensor_id", "fps", "width", "height", "encoding", "max_age_ms")
"""The keywords of the specification's form that are the sensor's own fields, not ``backend_params``."""


__all__ = ["OpenCVThreadParams", "OpenCVThreadSensorReader"]
