"""``MujocoCameraSensorReader``: a named camera of the MuJoCo twin, rendered off the tick thread.

The reader owns one daemon thread that renders at the sensor's fps on an absolute schedule
(frame k is due at ``t0 + k / fps``; a render slower than the period skips to the next future
slot, never bursts). Each frame:

1. under the twin's physics lock (:meth:`MujocoTwinHAL.locked_scene`), copy ``qpos``, the mocap
   poses and ``time`` into the renderer's private ``MjData`` and read the monotonic clock: tens
   of microseconds, so physics and the tick never wait for a render;
2. outside the lock, pose and render the private copy (:class:`OffscreenRenderer`: tens of ms on
   a CPU, with the GIL released while MuJoCo draws).

**Stamps.** ``SensorFrame.stamp_ns`` is the monotonic time read under the lock, right after the
copy: the moment the copied state was the twin's current state. The twin keeps simulated time
level with the clock, catching up every ``sync_period_s``, so a frame shows the physics of at
most ``sync_period_s`` plus one timestep before its stamp. This holds for any
``realtime_factor`` and across skipped backlogs, because simulated time is never converted into
wall time. The simulated time a frame shows is :meth:`MujocoCameraSensorReader.sim_time_s`;
``frame_id`` is the camera's name.

**Threads.** The OpenGL context is created, used and freed on the render thread (EGL and OSMesa
contexts are bound to a thread), and that thread drops a real-time scheduling policy inherited
from its creator, so neither it nor the software rasterizer's threads compete with a
``SCHED_FIFO`` tick.
"""

from __future__ import annotations

import difflib
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import (
    FrameEncoding,
    RobotManifest,
    ROSConfigError,
    ROSDependencyMissing,
    ROSRuntimeError,
    SensorFrame,
    SensorReaderConfig,
)
from openral_hal.mujoco_twin import MujocoTwinHAL
from openral_runner.backends.mujoco_render import (
    GLBackend,
    OffscreenRenderer,
    gl_setup_error,
    resolve_gl_backend,
)
from openral_runner.frame_slot import LatestFrameSlot, SlotReader, frame_from_array
from openral_runner.realtime import leave_realtime_scheduling
from openral_runner.sensor_reader import backend_params_field, validate_backend_params

try:
    import mujoco
except ImportError as exc:  # pragma: no cover - the twin HAL import above already needs it
    raise ROSDependencyMissing("mujoco", extra="twin", needed_for="the mujoco_camera sensor backend") from exc

_log = structlog.get_logger(__name__)

DEFAULT_WIDTH = 320
DEFAULT_HEIGHT = 240
DEFAULT_MESH_CELL_MM = 2.0

OPEN_TIMEOUT_S = 30.0
"""How long ``open()`` waits for the GL context, the model upload and the first frame."""

JOIN_TIMEOUT_S = 5.0
"""How long ``close()`` waits for the render thread (one render is well under a second)."""

_SIM_TIME_RING = 256
"""How many recent frames :meth:`MujocoCameraSensorReader.sim_time_s` remembers."""

_RENDER_MS_SMOOTHING = 0.1


class MujocoCameraParams(BaseModel):
    """``backend_params`` of the ``mujoco_camera`` backend.

    fps, width (default 320), height (default 240), encoding (``rgb8`` or ``bgr8``) and
    max_age_ms come from the sensor's own fields.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    camera: str | None = Field(
        default=None, min_length=1, description="camera name in the model; default: the robot's first camera"
    )
    gl: GLBackend | None = Field(
        default=None,
        description="OpenGL backend; default: the process's PYOPENGL_PLATFORM or MUJOCO_GL, else egl if an "
        "EGL device initialises, else osmesa",
    )
    mesh_cell_mm: float = Field(
        default=DEFAULT_MESH_CELL_MM,
        ge=0,
        le=50,
        allow_inf_nan=False,
        description="render the model's meshes simplified to a grid of this cell (millimetres): a CPU renderer's "
        "cost is in the vertices, and at camera resolutions a 2 mm grid is invisible; 0 renders the full meshes",
    )


class MujocoCameraSensorReader(SlotReader):
    """Renders one camera of a running :class:`MujocoTwinHAL` on its own thread; serves the latest frame.

    Built from the sensor's block and its validated ``backend_params``, whole: fps is the render
    rate (the delivered rate is lower when one render takes longer than a period), width and
    height default to 320x240, encoding is ``rgb8`` (as MuJoCo renders) or ``bgr8``.

    Args:
        config: The sensor's block of the deployment.
        params: The backend's options.
        hal: The twin whose scene is rendered.
        robot: The manifest whose first ``mujoco.cameras`` entry is the camera when ``params``
            names none (the twin's own manifest when ``None``).

    Attributes:
        camera: The camera's name in the twin's model.
        width / height: The image size rendered.
        gl: The OpenGL backend: ``params.gl``, or the one chosen at ``open()`` (see :func:`resolve_gl_backend`).

    Raises:
        ROSConfigError: ``hal`` is not a twin, an unknown camera or none to default to, or an
            unsupported encoding.
    """

    def __init__(
        self,
        config: SensorReaderConfig,
        params: MujocoCameraParams,
        *,
        hal: MujocoTwinHAL,
        robot: RobotManifest | None = None,
    ) -> None:
        sensor_id = config.sensor_id
        _require_twin(hal, sensor_id)
        if config.encoding not in (FrameEncoding.RGB8, FrameEncoding.BGR8):
            raise ROSConfigError(
                f"sensor '{sensor_id}': the mujoco_camera backend cannot deliver {config.encoding.value}",
                field="encoding",
                hint="use encoding rgb8 or bgr8",
            )
        self.config = config
        self.params = params
        self.sensor_id = sensor_id
        self.hal = hal
        self.camera = params.camera or _default_camera(robot or hal.manifest, hal, config)
        self.camera_id = _camera_id(hal.model, self.camera, sensor_id)
        self.width = config.width or DEFAULT_WIDTH
        self.height = config.height or DEFAULT_HEIGHT
        self.gl: GLBackend | None = params.gl
        self._triangles = (0, 0)
        self._slot = LatestFrameSlot(sensor_id, default_max_age_ms=config.max_age_ms)
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._setup_error: Exception | None = None
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._skipped = 0
        self._sim_times: list[tuple[int, float]] = [(-1, 0.0)] * _SIM_TIME_RING
        self._render_ms = 0.0
        self._render_ms_max = 0.0
        self._lock_us_max = 0.0

    @classmethod
    def from_config(
        cls,
        config: SensorReaderConfig,
        *,
        hal: Any,
        robot: RobotManifest | None,
        base_dir: Path | None = None,
    ) -> MujocoCameraSensorReader:
        """Plugin constructor; ``backend_params`` are validated as :class:`MujocoCameraParams`.

        Args:
            config: The sensor's block of the deployment.
            hal: Must be the :class:`MujocoTwinHAL` (``hal.adapter: mujoco_twin``).
            robot: Its manifest; its first ``mujoco.cameras`` entry is the default camera.
            base_dir: Unused.

        Raises:
            ROSConfigError: A wrong parameter (named, with the allowed keys), another HAL, or
                an unknown camera (the message lists the model's cameras).
        """
        params = validate_backend_params(MujocoCameraParams, config, backend="mujoco_camera")
        return cls(config, params, hal=_require_twin(hal, config.sensor_id), robot=robot)

    # -- lifecycle -----------------------------------------------------------------------

    def open(self) -> None:
        """Start the render thread and wait until it has delivered its first frame. Idempotent.

        The render thread resolves the GL backend (:func:`resolve_gl_backend`) and sets
        ``MUJOCO_GL`` to it if unset, so that a process spawned from this one renders the same way.

        Raises:
            ROSConfigError: The GL backend conflicts with the process's, or its system library is missing.
            ROSRuntimeError: The context, the model upload or the first render failed or timed out.
        """
        if self.is_open:
            return
        self._seq = 0
        self._skipped = 0
        self._sim_times = [(-1, 0.0)] * _SIM_TIME_RING
        self._render_ms = self._render_ms_max = self._lock_us_max = 0.0
        self._setup_error = None
        self._stop.clear()
        self._ready.clear()
        self._slot.open()
        thread = threading.Thread(target=self._run, name=f"openral-mujoco-camera-{self.sensor_id}", daemon=True)
        self._thread = thread
        thread.start()
        if not self._ready.wait(OPEN_TIMEOUT_S):
            self.close()
            raise ROSRuntimeError(
                f"sensor '{self.sensor_id}': no frame from camera '{self.camera}' within {OPEN_TIMEOUT_S:.0f} s "
                f"of opening ({self.gl or 'OpenGL'} rendering)"
            )
        if self._setup_error is not None:
            error = self._setup_error
            self.close()
            raise error
        _log.info("mujoco camera opened", sensor=self.sensor_id, camera=self.camera, gl=self.gl, fps=self.config.fps)

    def close(self) -> None:
        """Stop and join the render thread, which frees its GL context. Idempotent."""
        thread, self._thread = self._thread, None
        self._stop_worker(self._stop, thread, timeout_s=JOIN_TIMEOUT_S)

    # -- reading -------------------------------------------------------------------------

    def sim_time_s(self, frame: SensorFrame) -> float:
        """The twin's simulated time (seconds) that ``frame`` shows.

        Raises:
            KeyError: ``frame`` is not one of this reader's last 256 frames.
        """
        seq, sim_time = self._sim_times[frame.seq % _SIM_TIME_RING]
        if frame.sensor_id != self.sensor_id or seq != frame.seq:
            raise KeyError(f"frame {frame.sensor_id}#{frame.seq} is not among the recent frames of '{self.sensor_id}'")
        return sim_time

    def report(self) -> dict[str, Any]:
        """Requested versus delivered rate, render cost, physics-lock hold time, frames and skipped slots."""
        return {
            "sensor_id": self.sensor_id,
            "camera": self.camera,
            "gl": self.gl,
            "width": self.width,
            "height": self.height,
            "encoding": self.config.encoding.value,
            "requested_fps": self.config.fps,
            "delivered_fps": round(self.delivered_fps, 2),
            "frames": self._slot.frames_published,
            "skipped": self._skipped,
            "render_ms": round(self._render_ms, 2),
            "render_ms_max": round(self._render_ms_max, 2),
            "lock_us_max": round(self._lock_us_max, 1),
            "triangles": self._triangles[1],
            "triangles_full": self._triangles[0],
            "advice": "render less often (fps) or smaller (width, height), simplify the meshes further "
            "(backend_params.mesh_cell_mm), or render on a GPU (gl: egl with its driver)",
        }

    # -- render thread -------------------------------------------------------------------

    def _run(self) -> None:
        """Set up GL on this thread, render the first frame, then render on schedule until stopped."""
        renderer: OffscreenRenderer | None = None
        try:
            try:
                leave_realtime_scheduling()
                gl = self.gl = resolve_gl_backend(self.gl)
                os.environ.setdefault("MUJOCO_GL", gl)
                renderer = OffscreenRenderer(
                    self.hal.model,
                    self.camera_id,
                    self.width,
                    self.height,
                    gl,
                    mesh_cell_m=self.params.mesh_cell_mm / 1e3,
                )
                self._triangles = renderer.triangles
                renderer.render()  # warm-up: the first draw compiles shaders and uploads meshes
                self._render_one(renderer)
            except Exception as exc:
                self._setup_error = gl_setup_error(exc, self.sensor_id, self.gl)
                return
            finally:
                self._ready.set()
            period_ns = round(1e9 / self.config.fps)
            due_ns = time.monotonic_ns() + period_ns
            while True:
                now_ns = time.monotonic_ns()
                if now_ns < due_ns and self._stop.wait((due_ns - now_ns) / 1e9):
                    break
                if self._stop.is_set():
                    break
                self._render_one(renderer)
                due_ns += period_ns
                now_ns = time.monotonic_ns()
                if now_ns >= due_ns:  # the render overran: skip to the next future slot
                    missed = (now_ns - due_ns) // period_ns + 1
                    due_ns += missed * period_ns
                    self._skipped += missed
        except Exception as exc:
            error = ROSRuntimeError(f"sensor '{self.sensor_id}': rendering camera '{self.camera}' failed: {exc}")
            error.__cause__ = exc
            self._slot.fail(error)
            _log.error("mujoco camera failed", sensor=self.sensor_id, error=str(exc))
        finally:
            if renderer is not None:
                renderer.free()

    def _render_one(self, renderer: OffscreenRenderer) -> None:
        """Copy the twin's state under its lock, render it outside, publish the frame."""
        private = renderer.data
        with self.hal.locked_scene() as (_, data):
            t_lock = time.perf_counter_ns()
            private.qpos[:] = data.qpos
            private.mocap_pos[:] = data.mocap_pos
            private.mocap_quat[:] = data.mocap_quat
            private.time = data.time
            stamp_ns = time.monotonic_ns()
            lock_ns = time.perf_counter_ns() - t_lock
        start_ns = time.perf_counter_ns()
        rgb = renderer.render()
        if self.config.encoding is FrameEncoding.BGR8:
            pixels = np.ascontiguousarray(rgb[::-1, :, ::-1])
        else:
            pixels = np.ascontiguousarray(rgb[::-1])
        pixels.flags.writeable = False
        render_ms = (time.perf_counter_ns() - start_ns) / 1e6
        seq = self._seq
        self._sim_times[seq % _SIM_TIME_RING] = (seq, float(private.time))
        self._slot.publish(
            frame_from_array(
                self.sensor_id, pixels, stamp_ns=stamp_ns, seq=seq, encoding=self.config.encoding, frame_id=self.camera
            )
        )
        self._seq = seq + 1
        previous = self._render_ms
        self._render_ms = render_ms if not previous else previous + _RENDER_MS_SMOOTHING * (render_ms - previous)
        self._render_ms_max = max(self._render_ms_max, render_ms)
        self._lock_us_max = max(self._lock_us_max, lock_ns / 1e3)


def _default_camera(manifest: RobotManifest, twin: MujocoTwinHAL, config: SensorReaderConfig) -> str:
    """The robot's first declared camera, for a sensor that names none.

    Raises:
        ROSConfigError: The robot declares no camera (the message lists the model's).
    """
    declared = manifest.mujoco.cameras if manifest.mujoco is not None else []
    if not declared:
        raise ROSConfigError(
            f"robot '{manifest.robot_id}' declares no camera and sensor '{config.sensor_id}' names none; "
            f"the model has: {', '.join(_camera_names(twin.model)) or 'no cameras'}",
            field=f"{backend_params_field(config)}.camera",
            hint="set backend_params.camera",
        )
    return declared[0]


def _require_twin(hal: Any, sensor_id: str) -> MujocoTwinHAL:
    """``hal`` if it is the MuJoCo twin.

    Raises:
        ROSConfigError: Any other HAL; the camera renders the twin's own scene.
    """
    if isinstance(hal, MujocoTwinHAL):
        return hal
    raise ROSConfigError(
        f"sensor '{sensor_id}' uses backend mujoco_camera, which renders the MuJoCo twin's scene, "
        f"but the HAL is {type(hal).__name__}",
        field="hal.adapter",
        hint="mujoco_camera needs hal.adapter: mujoco_twin; for a real robot use opencv_thread or gstreamer",
    )


def _camera_names(model: Any) -> list[str]:
    return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) or f"#{i}" for i in range(model.ncam)]


def _camera_id(model: Any, camera: str, sensor_id: str) -> int:
    """The id of ``camera`` in ``model``.

    Raises:
        ROSConfigError: No such camera; lists the model's cameras and the closest name.
    """
    camera_id = int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera))
    if camera_id >= 0:
        return camera_id
    names = _camera_names(model)
    close = difflib.get_close_matches(camera, names, n=1)
    raise ROSConfigError(
        f"sensor '{sensor_id}': the twin's model has no camera '{camera}'; its cameras: {', '.join(names) or 'none'}",
        field=f"sensors[{sensor_id}].backend_params.camera",
        hint=f"did you mean '{close[0]}'?" if close else "set backend_params.camera to one of the model's cameras",
    )


__all__ = ["MujocoCameraParams", "MujocoCameraSensorReader"]
