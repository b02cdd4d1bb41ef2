"""Camera views of a MuJoCo simulator's state, rendered headless (shadows, reflections and MSAA off).

One :class:`~openral_runner.backends.mujoco_render.OffscreenRenderer` per camera and size, made on
first use: the simulator's state (``qpos``, mocap poses) is copied into the renderer's private
data, so rendering never touches the simulation. Single-threaded, like the runner's tick.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np

from openral_core import PixelBox, ROSConfigError, ROSRuntimeError
from openral_runner.backends.mujoco_render import GL_PACKAGES, GLBackend, OffscreenRenderer, resolve_gl_backend

try:
    import mujoco
except ImportError as exc:  # pragma: no cover - the adapters that use this import mujoco first
    from openral_core import ROSDependencyMissing

    raise ROSDependencyMissing("mujoco", extra="twin", needed_for="simulated cameras") from exc


def camera_names(model: Any) -> list[str]:
    """The named cameras of ``model``."""
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
    return [n for n in names if n]


def check_cameras(model: Any, requested: list[str], *, env: str) -> None:
    """Refuse a scene camera the model does not have, listing the ones it has.

    Raises:
        ROSConfigError: Naming ``cameras``.
    """
    known = camera_names(model)
    for name in requested:
        if name not in known:
            raise ROSConfigError(f"{env} has no camera {name!r}", field="cameras", hint=f"choose from {known}")


class MujocoViews:
    """Renders named cameras of ``model`` showing the state of ``data``.

    Args:
        model: The simulator's model.
        data: The simulator's data.
        env: Names the simulator in errors.
        gl: OpenGL backend; the process's by default (:func:`resolve_gl_backend`).
        moves_model: The simulator moves bodies and sites in the model itself (MetaWorld places
            goals, drawers and doors at reset; LIBERO recolours sites): their poses and site
            colours are copied before each frame too.
    """

    def __init__(
        self, model: Any, data: Any, *, env: str, gl: GLBackend | None = None, moves_model: bool = False
    ) -> None:
        self.model = model
        self.data = data
        self.env = env
        self.gl = gl
        self.moves_model = moves_model
        self._renderers: dict[tuple[str, int, int], OffscreenRenderer] = {}

    def render(self, camera: str, width: int, height: int) -> np.ndarray:
        """An ``(height, width, 3)`` RGB frame, top row first.

        Raises:
            ROSConfigError: No such camera, or the OpenGL backend's system library is missing.
            ROSRuntimeError: No OpenGL context could be created.
        """
        return np.ascontiguousarray(self._posed(camera, width, height).render()[::-1])

    def depth(self, camera: str, width: int, height: int) -> np.ndarray:
        """An ``(height, width)`` depth image in metres along the view axis, top row first (``inf``: nothing)."""
        renderer = self._posed(camera, width, height)
        return np.ascontiguousarray(renderer.render_depth()[::-1])

    def points(self, camera: str, width: int, height: int) -> np.ndarray:
        """The ``(N, 3)`` world points the camera's depth sees (one per pixel that hit something)."""
        depth = self.depth(camera, width, height)
        position, rotation, focal = self._camera_geometry(camera, height)
        rows, cols = np.nonzero(np.isfinite(depth))
        z = depth[rows, cols].astype(np.float64)
        # Camera frame: x right, y up, looking along -z (MuJoCo's convention).
        x = (cols + 0.5 - width / 2) / focal * z
        y = -(rows + 0.5 - height / 2) / focal * z
        local = np.stack([x, y, -z], axis=1)
        return np.asarray(local @ rotation.T + position)

    def project(self, points: np.ndarray, camera: str, width: int, height: int) -> np.ndarray:
        """Pixel coordinates ``(u, v)`` (top-left origin) of world ``points`` in the camera's image."""
        position, rotation, focal = self._camera_geometry(camera, height)
        local = (np.asarray(points, dtype=np.float64) - position) @ rotation
        depth = -local[:, 2]
        u = width / 2 + focal * local[:, 0] / depth
        v = height / 2 - focal * local[:, 1] / depth
        return np.stack([u, v], axis=1)

    def project_geom(self, geom: str, camera: str, width: int, height: int) -> PixelBox:
        """The image box of a geom's bounding box corners (clipped to the image): a detector's ground truth."""
        geom_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, geom)
        if geom_id < 0:
            raise ROSConfigError(f"{self.env} has no geom {geom!r}", field="geom")
        mujoco.mj_kinematics(self.model, self.data)
        centre = self.data.geom_xpos[geom_id]
        rotation = self.data.geom_xmat[geom_id].reshape(3, 3)
        half = self.model.geom_size[geom_id]
        signs = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
        corners = centre + (signs * half) @ rotation.T
        uv = self.project(corners, camera, width, height)
        return PixelBox(
            x0=float(np.clip(uv[:, 0].min(), 0, width)),
            y0=float(np.clip(uv[:, 1].min(), 0, height)),
            x1=float(np.clip(uv[:, 0].max(), 0, width)),
            y1=float(np.clip(uv[:, 1].max(), 0, height)),
        )

    def _posed(self, camera: str, width: int, height: int) -> OffscreenRenderer:
        key = (camera, width, height)
        renderer = self._renderers.get(key)
        if renderer is None:
            renderer = self._renderers[key] = self._make_renderer(camera, width, height)
        if self.moves_model:
            renderer.model.body_pos[:] = self.model.body_pos
            renderer.model.body_quat[:] = self.model.body_quat
            renderer.model.site_pos[:] = self.model.site_pos
            renderer.model.site_rgba[:] = self.model.site_rgba  # LIBERO lights a stove burner by a site's alpha
        target = renderer.data
        target.qpos[:] = self.data.qpos
        if self.model.nmocap:
            target.mocap_pos[:] = self.data.mocap_pos
            target.mocap_quat[:] = self.data.mocap_quat
        return renderer

    def _camera_geometry(self, camera: str, height: int) -> tuple[np.ndarray, np.ndarray, float]:
        camera_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if camera_id < 0:
            check_cameras(self.model, [camera], env=self.env)
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        position = np.array(self.data.cam_xpos[camera_id])
        rotation = np.array(self.data.cam_xmat[camera_id]).reshape(3, 3)
        focal = 0.5 * height / math.tan(math.radians(float(self.model.cam_fovy[camera_id])) / 2)
        return position, rotation, focal

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.free()
        self._renderers.clear()

    def _make_renderer(self, camera: str, width: int, height: int) -> OffscreenRenderer:
        camera_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if camera_id < 0:
            check_cameras(self.model, [camera], env=self.env)
        gl = resolve_gl_backend(self.gl)
        try:
            return OffscreenRenderer(self.model, camera_id, width, height, gl)
        except ImportError as exc:
            raise ROSConfigError(
                f"camera {camera!r}: {gl} rendering is unavailable: {exc}",
                field="env_kwargs.gl",
                hint=f"install the system packages {GL_PACKAGES[gl]}",
            ) from exc
        except RuntimeError as exc:
            raise ROSRuntimeError(
                f"camera {camera!r}: cannot start {gl} rendering: {exc} (check the packages {GL_PACKAGES[gl]})"
            ) from exc
