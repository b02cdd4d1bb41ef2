"""``LeRobotCameraSensorReader``: any LeRobot camera (opencv, zmq, intelrealsense, a plugin's) as a sensor.

The deployment names LeRobot's camera type and LeRobot's own keys::

    backend: lerobot_camera
    backend_params: {type: zmq, server_address: 127.0.0.1, port: 5555, camera_name: head}

The keys are decoded by LeRobot's own config class (its defaults and checks), when the deployment
is built and without opening anything. ``fps``, ``width`` and ``height`` are the sensor's own
fields, handed to LeRobot (fps only when the sensor sets it: a video file refuses a rate).
openral adds three keys of its own: ``type``, ``read_timeout_ms`` and ``max_read_failures``.

Capture runs on openral's thread, like every backend: it waits for each new frame, stamps it,
converts it to the sensor's encoding and publishes it into the frame slot. LeRobot 0.6's cameras
start a reader thread of their own in ``connect()`` that cannot be turned off, and their
``read()`` is a wait on that thread with a fixed 10 s timeout that first discards the frame
already waiting; so openral's thread calls ``async_read`` (LeRobot's "next frame not yet
returned") with the deployment's own timeout instead: it never gets a frame twice, and never
waits on a frame that has already arrived. The camera's warm-up (LeRobot's ``warmup_s``) is read
on openral's side too, after ``connect(warmup=False)``.

Colour: LeRobot delivers frames in its config's ``color_mode`` (RGB unless set; for ``zmq``, the
order the publisher encoded, RGB for LeRobot's ``image_server``); openral converts them to the
sensor's ``encoding`` (bgr8, rgb8 or mono8), and leaves them as they are when they already match.

Capture stamps are LeRobot's own capture instants carried onto the runner's clock: LeRobot's
built-in cameras note ``time.perf_counter()`` as each frame is read, and the frame's age on
that clock is subtracted from the runner's clock when the frame arrives. A camera that does not
say when it captured is stamped on arrival.

Failure handling is opencv_thread's: a read that brings no new frame within ``read_timeout_ms``
(or fails) counts, and ``max_read_failures`` in a row latch a failure the runner reports; in
between, the last frame ages and turns stale after the sensor's ``max_age_ms``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import FrameEncoding, ROSConfigError, ROSHardwareError, ROSRuntimeError, SensorReaderConfig
from openral_core.config import validate_model
from openral_core.config_files import require_user_file
from openral_hal.lerobot.device_config import build_device_config, require_lerobot
from openral_runner.frame_slot import LatestFrameSlot, SlotReader, frame_from_array
from openral_runner.sensor_reader import backend_params_field, is_file_path

_log = structlog.get_logger(__name__)

NEEDED_FOR = "the lerobot_camera sensor backend"

SENSOR_FIELDS = ("fps", "width", "height")
"""LeRobot camera keys that are the sensor's own fields: set on the sensor, handed to LeRobot from there."""

ENCODINGS = frozenset({FrameEncoding.BGR8, FrameEncoding.RGB8, FrameEncoding.MONO8})

WAIT_SLICE_S = 0.05
"""A read waits for LeRobot's next frame in slices this long, so ``close()`` is not held up by a read timeout."""

JOIN_TIMEOUT_S = 5.0
"""How long ``close()`` waits for the capture thread, which disconnects the camera (LeRobot's own joins take 2 s)."""


class LeRobotCameraParams(BaseModel):
    """openral's own keys of a ``lerobot_camera`` sensor's ``backend_params``; every other key is LeRobot's."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    type: str = Field(min_length=1, description="LeRobot's camera type: opencv, zmq, intelrealsense or a plugin's")
    read_timeout_ms: float = Field(
        default=1000.0, gt=0, le=600_000, description="a read that brings no new frame in this long counts as failed"
    )
    max_read_failures: int = Field(default=10, ge=1, description="failed reads in a row before the sensor fails")


OWN_KEYS = frozenset(LeRobotCameraParams.model_fields)


class LeRobotCameraSensorReader(SlotReader):
    """One LeRobot camera, read on openral's capture thread into the frame slot.

    Attributes:
        config: The sensor's fields (fps, size, encoding, staleness limit).
        params: openral's keys (type, read timeout, failures before failing).
        lerobot_config: LeRobot's camera config, as LeRobot decoded it.
    """

    def __init__(
        self,
        config: SensorReaderConfig,
        params: LeRobotCameraParams,
        lerobot_config: Any,
        *,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.config = config
        self.params = params
        self.lerobot_config = lerobot_config
        self.sensor_id = config.sensor_id
        self._clock_ns = clock_ns
        self._slot = LatestFrameSlot(config.sensor_id, default_max_age_ms=config.max_age_ms, clock_ns=clock_ns)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._read_failures = 0
        self._size: tuple[int, int] | None = None

    @classmethod
    def from_config(
        cls, config: SensorReaderConfig, *, hal: Any, robot: Any, base_dir: Path | None = None
    ) -> LeRobotCameraSensorReader:
        """Decode ``backend_params`` with LeRobot's config class; nothing is opened.

        Args:
            config: The sensor's block of the deployment.
            hal: Unused (the camera is not part of the HAL).
            robot: Unused.
            base_dir: Folder a relative video file (``index_or_path``) is resolved against.

        Raises:
            ROSDependencyMissing: LeRobot is not installed.
            ROSConfigError: An unknown type, a wrong, missing or misplaced key (named as
                ``sensors[<id>].backend_params.<key>``), or an encoding LeRobot cannot deliver.
        """
        require_lerobot(NEEDED_FOR)
        field = backend_params_field(config)
        raw = dict(config.backend_params)
        params = validate_model(
            LeRobotCameraParams,
            {key: value for key, value in raw.items() if key in OWN_KEYS},
            source="the lerobot_camera sensor backend",
            field_prefix=field,
        )
        if config.encoding not in ENCODINGS:
            raise ROSConfigError(
                f"a LeRobot camera delivers colour images, not {config.encoding}",
                field=f"sensors[{config.sensor_id}].encoding",
                hint="use encoding bgr8, rgb8 or mono8",
            )
        lerobot_params = _lerobot_params(config, raw, base_dir)
        return cls(config, params, build_device_config("camera", params.type, lerobot_params, field=field))

    # -- lifecycle -----------------------------------------------------------------------

    def open(self) -> None:
        """Connect the LeRobot camera, wait for a first frame, check its size and start capturing.

        Idempotent.

        Raises:
            ROSHardwareError: LeRobot cannot connect the camera, or it delivers no frame in time.
            ROSConfigError: The camera delivers another size than the sensor asks for.
        """
        if self.is_open:
            return
        stop = threading.Event()  # a fresh one: a thread stuck from a previous run keeps its own
        camera = self._connect()
        try:
            first = self._first_frame(camera, stop)
        except BaseException:
            _disconnect(camera, self.sensor_id)
            raise
        self._seq = 0
        self._read_failures = 0
        self._stop = stop
        self._slot.open()
        self._publish(*first)
        self._thread = threading.Thread(
            target=self._run, args=(camera, self._stop), name=f"openral-lerobot-{self.sensor_id}", daemon=True
        )
        self._thread.start()
        _log.info("lerobot camera opened", sensor=self.sensor_id, type=self.params.type, size=self._size)

    def close(self) -> None:
        """Stop the capture thread, which disconnects the camera. Idempotent."""
        thread, self._thread = self._thread, None
        self._stop_worker(self._stop, thread, timeout_s=JOIN_TIMEOUT_S)

    def report(self) -> dict[str, Any]:
        """Requested versus delivered: rate, size, frames captured, failed reads."""
        width, height = self._size or (None, None)
        return {
            "sensor_id": self.sensor_id,
            "device": f"lerobot {self.params.type}",
            "requested_fps": self.config.fps,
            "delivered_fps": round(self.delivered_fps, 2),
            "requested_size": (self.config.width, self.config.height),
            "width": width,
            "height": height,
            "encoding": self.config.encoding.value,
            "frames": self._slot.frames_published,
            "read_failures": self._read_failures,
        }

    # -- opening -------------------------------------------------------------------------

    def _connect(self) -> Any:
        """LeRobot's camera for the config, made by LeRobot's own factory and connected."""
        from lerobot.cameras.utils import make_cameras_from_configs  # noqa: PLC0415  (the extra)

        camera = None
        try:
            camera = make_cameras_from_configs({self.sensor_id: self.lerobot_config})[self.sensor_id]
            camera.connect(warmup=False)  # warmed up by _first_frame
        except Exception as exc:
            if getattr(camera, "thread", None) is not None:  # a reader thread LeRobot left running
                _disconnect(camera, self.sensor_id)
            raise ROSHardwareError(
                f"sensor '{self.sensor_id}': LeRobot's {self.params.type} camera did not connect: {exc}"
            ) from exc
        return camera

    def _first_frame(self, camera: Any, stop: threading.Event) -> tuple[int, np.ndarray]:
        """The last frame of the camera's warm-up (LeRobot's ``warmup_s``: frames read and dropped); its size must
        be the sensor's.

        The warm-up is done here, not in LeRobot's ``connect()``: LeRobot 0.6's zmq camera, when its
        warm-up gets no frame, closes its socket under its own running reader thread and hangs there.
        """
        warm_until = time.monotonic() + float(getattr(self.lerobot_config, "warmup_s", 0) or 0)
        try:
            first = self._capture(camera, stop)
            while time.monotonic() < warm_until:
                first = self._capture(camera, stop)
        except Exception as exc:
            raise ROSHardwareError(
                f"sensor '{self.sensor_id}': LeRobot's {self.params.type} camera connected but delivered no frame "
                f"within {self.params.read_timeout_ms:g} ms: {exc}"
            ) from exc
        height, width = first[1].shape[:2]
        wanted = (self.config.width or width, self.config.height or height)
        if wanted != (width, height):
            raise ROSConfigError(
                f"sensor '{self.sensor_id}': requested {wanted[0]}x{wanted[1]}, "
                f"but LeRobot's {self.params.type} camera delivers {width}x{height}",
                hint=f"set width: {width} and height: {height}, or leave them unset",
            )
        self._size = (width, height)
        return first

    # -- capture thread ------------------------------------------------------------------

    def _capture(self, camera: Any, stop: threading.Event) -> tuple[int, np.ndarray]:
        """Wait for LeRobot's next frame; stamp it at its capture and convert it to the sensor's encoding.

        Raises:
            TimeoutError: No new frame within ``read_timeout_ms``, or ``stop`` was set meanwhile.
        """
        give_up = time.monotonic() + self.params.read_timeout_ms / 1e3
        while True:
            wait_s = min(WAIT_SLICE_S, give_up - time.monotonic())
            try:
                pixels = camera.async_read(timeout_ms=max(wait_s, 0.001) * 1e3)
                break
            except TimeoutError:
                if stop.is_set() or time.monotonic() >= give_up:
                    raise
        captured_at = _lerobot_stamp(camera, pixels)
        # perf_counter first: a pause between the two readings makes the stamp later, never earlier than the capture.
        age_ns = 0 if captured_at is None else max(0, round((time.perf_counter() - captured_at) * 1e9))
        stamp_ns = self._clock_ns() - age_ns
        return stamp_ns, _to_encoding(pixels, _colour_order(self.lerobot_config), self.config.encoding)

    def _publish(self, stamp_ns: int, pixels: np.ndarray) -> None:
        self._slot.publish(
            frame_from_array(self.sensor_id, pixels, stamp_ns=stamp_ns, seq=self._seq, encoding=self.config.encoding)
        )
        self._seq += 1

    def _run(self, camera: Any, stop: threading.Event) -> None:
        """Capture until stopped or until ``max_read_failures`` reads in a row brought no frame."""
        period_s = 1.0 / self.config.fps
        failures = 0
        try:
            while not stop.is_set():
                try:
                    captured = self._capture(camera, stop)
                except Exception as exc:  # a timeout, or LeRobot's reader thread has stopped
                    if stop.is_set():
                        break
                    failures += 1
                    self._read_failures += 1
                    if failures >= self.params.max_read_failures:
                        raise ROSRuntimeError(
                            f"sensor '{self.sensor_id}': LeRobot's {self.params.type} camera delivered no frame "
                            f"in {failures} reads in a row ({type(exc).__name__}: {exc})"
                        ) from exc
                    if not isinstance(exc, TimeoutError):
                        stop.wait(period_s)  # a read that failed at once: do not spin
                    continue
                failures = 0
                self._publish(*captured)
        except ROSRuntimeError as exc:
            self._slot.fail(exc)
        except Exception as exc:
            error = ROSRuntimeError(f"sensor '{self.sensor_id}': capture from LeRobot's camera failed: {exc}")
            error.__cause__ = exc
            self._slot.fail(error)
        finally:
            _disconnect(camera, self.sensor_id)


def _lerobot_params(config: SensorReaderConfig, raw: Mapping[str, Any], base_dir: Path | None) -> dict[str, Any]:
    """LeRobot's keys of ``backend_params``, with the sensor's size and rate and a resolved video file."""
    field = backend_params_field(config)
    params = {key: value for key, value in raw.items() if key not in OWN_KEYS}
    for name in SENSOR_FIELDS:
        if name in params:
            raise ROSConfigError(
                f"{name} is the sensor's own field, not a backend parameter",
                field=f"{field}.{name}",
                hint=f"set {name} on the sensor (sensors[{config.sensor_id}].{name})",
            )
    if config.width is not None:
        params["width"] = config.width
    if config.height is not None:
        params["height"] = config.height
    if "fps" in config.model_fields_set:
        if not float(config.fps).is_integer():
            raise ROSConfigError(
                f"LeRobot cameras take a whole number of frames per second, not {config.fps:g}",
                field=f"sensors[{config.sensor_id}].fps",
            )
        params["fps"] = int(config.fps)
    source = params.get("index_or_path")
    if isinstance(source, str) and is_file_path(source):
        params["index_or_path"] = str(
            require_user_file(source, base_dir, field=f"{field}.index_or_path", what="video file")
        )
    return params


def _colour_order(lerobot_config: Any) -> str:
    """The channel order LeRobot's camera delivers: its ``color_mode`` (LeRobot's default, RGB, without one)."""
    mode = getattr(lerobot_config, "color_mode", None)
    return str(getattr(mode, "value", mode) or "rgb")


def _to_encoding(pixels: np.ndarray, order: str, encoding: FrameEncoding) -> np.ndarray:
    """``pixels`` (``order``, or one channel) in the sensor's encoding; as they are when they already are."""
    import cv2  # noqa: PLC0415  (comes with the lerobot extra)

    if pixels.ndim == 2:
        codes = {FrameEncoding.BGR8: cv2.COLOR_GRAY2BGR, FrameEncoding.RGB8: cv2.COLOR_GRAY2RGB}
    elif order == "bgr":
        codes = {FrameEncoding.RGB8: cv2.COLOR_BGR2RGB, FrameEncoding.MONO8: cv2.COLOR_BGR2GRAY}
    else:
        codes = {FrameEncoding.BGR8: cv2.COLOR_RGB2BGR, FrameEncoding.MONO8: cv2.COLOR_RGB2GRAY}
    code = codes.get(encoding)
    return pixels if code is None else cv2.cvtColor(pixels, code)


def _lerobot_stamp(camera: Any, pixels: np.ndarray) -> float | None:
    """When LeRobot captured ``pixels`` (its ``time.perf_counter()``), or ``None`` when it does not say.

    LeRobot's built-in cameras keep the latest frame and its stamp under ``frame_lock``; the stamp
    is used only while it still belongs to this very frame.
    """
    lock = getattr(camera, "frame_lock", None)
    if lock is None:
        return None
    with lock:
        latest = getattr(camera, "latest_frame", None)
        stamp = getattr(camera, "latest_timestamp", None)
    return stamp if latest is pixels and isinstance(stamp, float) else None


def _disconnect(camera: Any, sensor_id: str) -> None:
    try:
        camera.disconnect()
    except Exception as exc:  # already disconnected, or its SDK failed while letting go
        _log.warning("lerobot camera did not disconnect cleanly", sensor=sensor_id, error=str(exc))


__all__ = ["LeRobotCameraParams", "LeRobotCameraSensorReader"]
