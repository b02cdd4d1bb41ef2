"""Importing openral_rskill and its built-in skills stays light: no heavy library is loaded."""

from __future__ import annotations

import subprocess
import sys

import openral_rskill

HEAVY = ["torch", "onnxruntime", "cv2", "mujoco", "gi", "rclpy", "zenoh", "av", "pyarrow", "opentelemetry.sdk"]


def test_import_loads_no_heavy_library() -> None:
    code = (
        "import sys\n"
        "import openral_rskill, openral_rskill.hello, openral_rskill.noop, openral_rskill.testing\n"
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_public_names() -> None:
    for name in ("RSkillBase", "rSkillBase", "RSkillManifest", "rSkill"):
        assert hasattr(openral_rskill, name), name
