"""``MUJOCO_GL``, checked once where the command starts, before any simulator reads it.

MuJoCo, dm_control and gymnasium each read ``MUJOCO_GL`` when they are imported or first render,
and each fails on a value it does not know with a bare ``RuntimeError`` from deep inside a run.
The values all three accept are ``egl``, ``osmesa`` and ``glfw``; anything else set is refused
here as a configuration error that names the backends this machine has.
"""

from __future__ import annotations

import ctypes.util
import importlib.util
import os
from collections.abc import Mapping
from typing import Final

from openral_core import ROSConfigError

VARIABLE: Final = "MUJOCO_GL"
PYOPENGL_VARIABLE: Final = "PYOPENGL_PLATFORM"
BACKENDS: Final = ("egl", "osmesa", "glfw")
"""The ``MUJOCO_GL`` values MuJoCo, dm_control and gymnasium all accept."""


def check_mujoco_gl(environ: Mapping[str, str] | None = None) -> None:
    """Refuse a ``MUJOCO_GL`` that the simulators cannot render with; unset is fine (each picks one).

    Raises:
        ROSConfigError: ``MUJOCO_GL`` is set to anything but egl, osmesa or glfw, or names egl or
            osmesa while ``PYOPENGL_PLATFORM`` names the other.
    """
    environ = os.environ if environ is None else environ
    value = environ.get(VARIABLE)
    platform = environ.get(PYOPENGL_VARIABLE)
    if value in ("egl", "osmesa") and platform and platform != value:
        # PyOpenGL binds one platform per process: MuJoCo's module for the other refuses to import.
        raise ROSConfigError(
            f"{value!r} cannot render while {PYOPENGL_VARIABLE} is {platform!r} (one OpenGL platform per process)",
            field=VARIABLE,
            hint=f"set both to the same backend, or unset {PYOPENGL_VARIABLE}",
        )
    if value is None or value in BACKENDS:
        return
    working = available_backends(environ)
    if working:
        hint = f"unset it, or set it to one that works on this machine: {', '.join(working)}"
    else:
        hint = (
            f"set it to one of {', '.join(BACKENDS)} once its library is installed: "
            "libegl1 libegl-mesa0 libgl1 (egl) or libosmesa6 (osmesa); none is found on this machine"
        )
    message = f"{value!r} is not one of the OpenGL backends the simulators accept ({', '.join(BACKENDS)})"
    raise ROSConfigError(message, field=VARIABLE, hint=hint)


def available_backends(environ: Mapping[str, str]) -> list[str]:
    """The backends this machine can render with, as far as can be told without creating a context.

    egl and osmesa need their shared library; glfw needs the ``glfw`` module and a display.
    """
    working = []
    if ctypes.util.find_library("EGL"):
        working.append("egl")
    if ctypes.util.find_library("OSMesa"):
        working.append("osmesa")
    has_display = bool(environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY"))
    if has_display and importlib.util.find_spec("glfw") is not None:
        working.append("glfw")
    return working
