"""Importing openral packages loads no heavy optional library (checked in a fresh interpreter)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

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
    "ray",
    "metaworld",
    "gym_pusht",
    "aiohttp",
    "matplotlib",
    "selenium",
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
        "openral_sim.runner",
        "openral_sim.evaluation",
        "openral_remote.codec",
        "openral_perception",
        "openral_perception.observer",
        "openral_perception.detectors.registry",
        "openral_perception.reward",
        "openral_runner.perception",
        "openral_runner.backends.gstreamer.perception_tee",
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


def _imported_by_the_command(*args: str) -> set[str]:
    """Every module ``python -m openral_cli ARGS`` imports, as ``-X importtime`` lists them."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "openral_cli", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    lines = [line for line in proc.stderr.splitlines() if line.startswith("import time:")]
    return {line.rsplit("|", 1)[-1].strip() for line in lines[1:]}  # the first line is the header


@pytest.mark.parametrize(
    "args",
    [("--help",), ("sim", "run", "--help"), ("benchmark", "run", "--help"), ("serve", "--help")],
    ids=" ".join,
)
def test_the_commands_help_loads_no_heavy_library(args: tuple[str, ...]) -> None:
    imported = _imported_by_the_command(*args)
    assert "openral_cli.main" in imported  # the listing is read: the command's own modules are in it
    heavy = sorted(m for m in imported if any(m == h or m.startswith(f"{h}.") for h in HEAVY))
    assert heavy == [], f"openral {' '.join(args)} loaded {heavy}"


def test_the_check_itself_detects_a_heavy_import() -> None:
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    code = "import sys, openral_hal.mujoco_twin; print('mujoco' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert proc.stdout.strip() == "True"


BLOCKER = """
import importlib.abc, importlib.metadata, json, sys

BLOCKED = {"mujoco", "cv2", "gi", "onnxruntime", "zenoh"}


class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r} (blocked)", name=name)
        return None


sys.meta_path.insert(0, Blocker())
from openral_core import ROSDependencyMissing

failed = {}
GROUPS = (
    "openral.skills",
    "openral.hals",
    "openral.sensor_backends",
    "openral.safety_clients",
    "openral.sim_envs",
    "openral.detectors",
)
for group in GROUPS:
    for ep in importlib.metadata.entry_points(group=group):
        try:
            ep.load()
        except ROSDependencyMissing as exc:
            failed[f"{group}:{ep.name}"] = [exc.module, exc.extra, str(exc)]
        except Exception as exc:
            failed[f"{group}:{ep.name}"] = ["not a ROSDependencyMissing", type(exc).__name__, str(exc)]
print(json.dumps(failed))
"""

NEEDS_A_HEAVY_LIBRARY = {
    "openral.hals:mujoco_twin": ("mujoco", "twin"),
    "openral.sensor_backends:mujoco_camera": ("mujoco", "twin"),
    "openral.sensor_backends:opencv_thread": ("cv2", "opencv"),
    "openral.sensor_backends:gstreamer": ("gi", "gstreamer"),
    "openral.skills:metaworld_expert": ("mujoco", "sim"),
    "openral.skills:onnx_policy": ("onnxruntime", "policy"),
    "openral.skills:remote_policy": ("zenoh", "remote"),
    "openral.sim_envs:so101": ("mujoco", "twin"),
    "openral.sim_envs:metaworld": ("mujoco", "twin"),
    "openral.sim_envs:pusht": ("cv2", "opencv"),
    "openral.sim_envs:aloha": ("mujoco", "aloha"),
    "openral.skills:aloha_transfer_cube_expert": ("mujoco", "aloha"),
    "openral.skills:aloha_insertion_expert": ("mujoco", "aloha"),
    "openral.sim_envs:libero": ("mujoco", "libero"),
    "openral.detectors:objects": ("onnxruntime", "policy"),
}


def test_only_plugins_that_need_a_heavy_library_fail_without_it_and_name_the_extra() -> None:
    proc = subprocess.run([sys.executable, "-c", BLOCKER], capture_output=True, text=True, timeout=60, check=True)
    failed = json.loads(proc.stdout)
    ros2 = failed.pop("openral.sensor_backends:ros2_image", None)
    if ros2 is not None:  # no ROS 2 here: it fails for rclpy, which no extra provides, and says so
        assert ros2[:2] == ["rclpy", None], ros2
        assert "ROS 2" in ros2[2]
    assert set(failed) == set(NEEDS_A_HEAVY_LIBRARY), failed
    for name, (module, extra) in NEEDS_A_HEAVY_LIBRARY.items():
        got_module, got_extra, message = failed[name]
        assert (got_module, got_extra) == (module, extra), failed[name]
        assert f"--extra {extra}" in message


def test_a_real_arm_deployment_validates_without_mujoco(tmp_path) -> None:
    pytest.importorskip("serial", reason="needs the 'serial' extra (pyserial)")
    code = BLOCKER.split("from openral_core import", maxsplit=1)[0] + (
        "from click.testing import CliRunner\n"
        "from openral_cli.main import cli\n"
        f"out = CliRunner().invoke(cli, ['validate', {str(ROOT / 'deployments' / 'so101_serial_emulated.yaml')!r}])\n"
        "print(out.exit_code, out.output)\n"
        "print('mujoco' in sys.modules)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    first, *_rest, last = proc.stdout.strip().splitlines()
    assert first.startswith("0 ok:"), proc.stdout
    assert last == "False"
