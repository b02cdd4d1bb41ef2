"""Camera views of a MuJoCo simulator's state, rendered headless (shadows, reflections and MSAA off).

One :class:`~openral_runner.backends.mujoco_render.OffscreenRenderer` per camera and size, made on
first use: the simulator's state (``qpos``, mocap poses) is copied into the renderer's private
data, so rendering never touches the simulation. Single-threaded, like the runner's tick.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from openral_core import ROSConfigError, ROSRuntimeError
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
            goals, drawers and doors at reset): their poses are copied before each frame too.
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
        key = (camera, width, height)
        renderer = self._renderers.get(key)
        if renderer is None:
            renderer = self._renderers[key] = self._make_renderer(camera, width, height)
        if self.moves_model:
            renderer.model.body_pos[:] = self.model.body_pos
            renderer.model.body_quat[:] = self.model.body_quat
            renderer.model.site_pos[:] = self.model.site_pos
        target = renderer.data
        target.qpos[:] = self.data.qpos
        if self.model.nmocap:
            target.mocap_pos[:] = self.data.mocap_pos
            target.mocap_quat[:] = self.data.mocap_quat
        return np.ascontiguousarray(renderer.render()[::-1])

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
