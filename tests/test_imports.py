"""Importing openral packages loads no heavy optional library (checked in a fresh interpreter)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = [
    "mujoco",
    "cv2",
    "gi",
    "torch",
    "onnxruntime",
    "opentelemetry.sdk",
    "av",
    "pyarrow",
    "rclpy",
    "zenoh",
    "foxglove",
    "mcap",
]


@pytest.mark.parametrize(
    "package",
    [
        "openral_core",
        "openral_observability",
        "openral_world_state",
        "openral_rskill",
        "openral_hal",
        "openral_runner",
        "openral_runner.factory",
        "openral_cli.main",
    ],
)
def test_import_loads_no_heavy_library(package: str) -> None:
    code = (
        "import importlib, json, sys\n"
        f"importlib.import_module({package!r})\n"
        f"print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert json.loads(proc.stdout) == [], f"importing {package} loaded {proc.stdout.strip()}"


def test_the_check_itself_detects_a_heavy_import() -> None:
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    code = "import sys, openral_hal.mujoco_twin; print('mujoco' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert proc.stdout.strip() == "True"
