"""Headless offscreen rendering of a MuJoCo model: the OpenGL backend choice and a thread-bound renderer.

Used by the ``mujoco_camera`` sensor backend and by the simulator envs that render their own cameras
(:mod:`openral_sim.envs.mujoco_views`, ALOHA). ``mujoco`` picks its default GL backend from
``MUJOCO_GL`` once, when it is imported (before this module runs), so the renderer here creates
its context explicitly from ``mujoco.egl`` or ``mujoco.osmesa``. PyOpenGL binds one platform per
process (``PYOPENGL_PLATFORM``, set by whichever of those is imported first), so one process
renders through one backend; :func:`resolve_gl_backend` chooses it.

An EGL or OSMesa context is bound to the thread that made it current: construct, use and free an
:class:`OffscreenRenderer` on one thread.
"""

from __future__ import annotations

import copy
import ctypes
import ctypes.util
import functools
import importlib
import os
from typing import Any, Literal

import numpy as np
import structlog

from openral_core import ROSConfigError, ROSDependencyMissing, ROSError, ROSRuntimeError
from openral_runner.backends.render_meshes import simplify_render_meshes

try:
    import mujoco
except ImportError as exc:  # pragma: no cover - exercised only without the extra
    raise ROSDependencyMissing("mujoco", extra="twin", needed_for="rendering the MuJoCo twin's cameras") from exc

_log = structlog.get_logger(__name__)

GLBackend = Literal["egl", "osmesa"]

GL_PACKAGES: dict[GLBackend, str] = {"egl": "libegl1 libegl-mesa0 libgl1", "osmesa": "libosmesa6 libgl1"}
"""Debian packages each backend needs (software rendering through Mesa)."""

_MAX_GEOM = 10_000
_EGL_PLATFORM_DEVICE_EXT = 0x313F


class OffscreenRenderer:
    """Renders one fixed camera of a private copy of ``model``; shadows, reflections and MSAA off.

    The copy gets an offscreen buffer of at least ``width`` × ``height`` and ``offsamples = 0``,
    and with ``mesh_cell_m`` > 0 its meshes are simplified to that grid
    (:func:`~openral_runner.backends.render_meshes.simplify_render_meshes`); the caller's model is
    not modified. Write the state to show into :attr:`data` (``qpos``,
    mocap poses), then call :meth:`render`. Every method must run on the constructing thread.

    Raises:
        ImportError: The backend's system library is missing, or PyOpenGL is bound to the other one.
        RuntimeError: No GL context could be created.
    """

    def __init__(
        self, model: Any, camera_id: int, width: int, height: int, gl: GLBackend, *, mesh_cell_m: float = 0.0
    ) -> None:
        gl_module = importlib.import_module(f"mujoco.{gl}")
        model = copy.deepcopy(model)
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        model.vis.quality.offsamples = 0
        triangles = int(model.mesh_facenum.sum())
        self.triangles: tuple[int, int] = (triangles, triangles)
        """The model's mesh triangles before and after simplification."""
        if mesh_cell_m > 0:
            self.triangles = simplify_render_meshes(model, mesh_cell_m)
        self.model = model
        self.data = mujoco.MjData(model)
        self._gl: Any = None
        self._context: Any = None
        try:
            self._gl = gl_module.GLContext(width, height)
            self._gl.make_current()
            self._context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100.value)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._context)
        except BaseException:
            self.free()
            raise
        self._scene = mujoco.MjvScene(model, maxgeom=_MAX_GEOM)
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        self._scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self._option = mujoco.MjvOption()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._camera.fixedcamid = camera_id
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._shape = (height, width, 3)

    def render(self) -> np.ndarray:
        """Pose :attr:`data` from its ``qpos`` and render it: a new ``(H, W, 3)`` RGB array, bottom row first.

        ``mj_fwdPosition`` computes body, camera and light poses (no dynamics). The MuJoCo calls
        release the GIL while they draw.
        """
        model, data = self.model, self.data
        mujoco.mj_fwdPosition(model, data)
        mujoco.mjv_updateScene(
            model, data, self._option, None, self._camera, mujoco.mjtCatBit.mjCAT_ALL.value, self._scene
        )
        mujoco.mjr_render(self._rect, self._scene, self._context)
        out = np.empty(self._shape, dtype=np.uint8)
        mujoco.mjr_readPixels(out, None, self._rect, self._context)
        return out

    def render_depth(self) -> np.ndarray:
        """Pose :attr:`data` and render its depth: a new ``(H, W)`` float32 array of metres along the view axis,
        bottom row first (``inf`` where nothing is within the far plane)."""
        model, data = self.model, self.data
        mujoco.mj_fwdPosition(model, data)
        mujoco.mjv_updateScene(
            model, data, self._option, None, self._camera, mujoco.mjtCatBit.mjCAT_ALL.value, self._scene
        )
        mujoco.mjr_render(self._rect, self._scene, self._context)
        buffer = np.empty(self._shape[:2], dtype=np.float32)
        mujoco.mjr_readPixels(None, buffer, self._rect, self._context)
        extent = float(model.stat.extent)
        near, far = float(model.vis.map.znear) * extent, float(model.vis.map.zfar) * extent
        with np.errstate(divide="ignore"):
            depth = near / (1.0 - buffer * (1.0 - near / far))
        depth[buffer >= 1.0] = np.inf
        return depth.astype(np.float32)

    def free(self) -> None:
        """Release the MuJoCo render context and the GL context. Idempotent."""
        context, self._context = self._context, None
        if context is not None:
            context.free()
        gl, self._gl = self._gl, None
        if gl is not None:
            gl.free()


def resolve_gl_backend(requested: GLBackend | None) -> GLBackend:
    """The OpenGL backend this process renders with.

    A PyOpenGL platform already set (``PYOPENGL_PLATFORM``) wins when nothing is requested and
    conflicts with a different request. Otherwise: the request; else ``MUJOCO_GL`` when it
    names egl or osmesa; else egl if an EGL device initialises (probed through ``ctypes``,
    which commits PyOpenGL to nothing), else osmesa.

    Raises:
        ROSConfigError: ``requested`` differs from the platform this process already uses, or
            ``PYOPENGL_PLATFORM`` names a platform that cannot render headless.
    """
    platform = os.environ.get("PYOPENGL_PLATFORM", "").strip().lower()
    if platform:
        committed = _as_backend(platform)
        if committed is None:
            raise ROSConfigError(
                f"PYOPENGL_PLATFORM is '{platform}', but the twin's camera renders headless with egl or osmesa",
                hint="unset PYOPENGL_PLATFORM or set it to egl or osmesa",
            )
        if requested is not None and requested != committed:
            raise ROSConfigError(
                f"cannot render with {requested}: this process's OpenGL platform is already "
                f"'{committed}' (PYOPENGL_PLATFORM), and there is one per process",
                field="backend_params.gl",
                hint=f"set gl: {committed} on every mujoco_camera sensor, or leave it unset",
            )
        return committed
    if requested is not None:
        return requested
    preferred = _as_backend(os.environ.get("MUJOCO_GL", "").strip().lower())
    if preferred is not None:
        return preferred
    return "egl" if egl_device_available() else "osmesa"


def _as_backend(name: str) -> GLBackend | None:
    if name == "egl":
        return "egl"
    if name == "osmesa":
        return "osmesa"
    return None


@functools.cache
def egl_device_available() -> bool:
    """Whether libEGL initialises a device display (what ``mujoco.egl`` needs), probed without PyOpenGL.

    The display is left initialised: ``mujoco.egl`` initialises it again (a no-op), and
    terminating it could pull it from under another renderer in this process.
    """
    name = ctypes.util.find_library("EGL")
    if name is None:
        return False
    try:
        egl = ctypes.CDLL(name)
        egl.eglGetProcAddress.restype = ctypes.c_void_p
        egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
        egl.eglInitialize.restype = ctypes.c_uint
        egl.eglInitialize.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
        query_address = egl.eglGetProcAddress(b"eglQueryDevicesEXT")
        display_address = egl.eglGetProcAddress(b"eglGetPlatformDisplayEXT")
        if not query_address or not display_address:
            return False
        query_devices = ctypes.CFUNCTYPE(
            ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_int)
        )(query_address)
        get_display = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p)(
            display_address
        )
        devices = (ctypes.c_void_p * 16)()
        count = ctypes.c_int(0)
        if not query_devices(16, devices, ctypes.byref(count)):
            return False
        for index in range(count.value):
            display = get_display(_EGL_PLATFORM_DEVICE_EXT, devices[index], None)
            if display and egl.eglInitialize(display, None, None):
                return True
    except (OSError, AttributeError):
        return False
    return False


def gl_setup_error(exc: Exception, sensor_id: str, gl: GLBackend | None) -> ROSError:
    """Translate a GL or MuJoCo set-up failure into the ``ROS*`` family, naming the fix."""
    if isinstance(exc, ROSError):
        return exc
    backend: GLBackend = gl or "egl"
    other = "osmesa" if backend == "egl" else "egl"
    error: ROSError
    if isinstance(exc, ImportError):
        error = ROSConfigError(
            f"sensor '{sensor_id}': {backend} rendering is unavailable: {exc}",
            field="backend_params.gl",
            hint=f"install the system packages {GL_PACKAGES[backend]}, or set gl: {other} in a fresh process",
        )
    else:
        error = ROSRuntimeError(
            f"sensor '{sensor_id}': cannot start {backend} rendering: {exc} "
            f"(check the packages {GL_PACKAGES[backend]}, or set gl: {other} in a fresh process)"
        )
    error.__cause__ = exc
    return error


__all__ = [
    "GL_PACKAGES",
    "GLBackend",
    "OffscreenRenderer",
    "egl_device_available",
    "gl_setup_error",
    "resolve_gl_backend",
]
