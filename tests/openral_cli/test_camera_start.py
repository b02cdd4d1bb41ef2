"""A camera that cannot deliver a fresh frame fails the start with its frame age, not a run of withheld ticks."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
TWIN_CAMERA = ROOT / "deployments" / "so101_twin_camera.yaml"

pytestmark = [pytest.mark.mujoco, pytest.mark.gl]


def test_a_camera_never_within_its_age_limit_fails_the_start_in_one_line(tmp_path: Path) -> None:
    pytest.importorskip("mujoco", reason="the twin's camera needs the 'twin' extra")
    config = yaml.safe_load(TWIN_CAMERA.read_text())
    config["sensors"][0]["max_age_ms"] = 0.5  # no CPU render is that quick: every frame is stale when read
    config["faults"]["sensor_ready_timeout_s"] = 1.0
    deployment = tmp_path / "camera.yaml"
    deployment.write_text(yaml.safe_dump(config))
    dataset = tmp_path / "data"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "openral_cli",
            "deploy",
            "--config",
            str(deployment),
            "--max-ticks",
            "30",
            "--dataset-out",
            str(dataset),
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    if "no headless OpenGL" in run.stderr or "rendering is unavailable" in run.stderr:
        pytest.skip(f"no headless OpenGL here: {run.stderr.strip().splitlines()[-1]}")
    assert run.returncode == 1, run.stderr
    errors = [line for line in run.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, run.stderr
    assert "sensor 'front' delivered no frame younger than 0.5 ms (its newest was" in errors[0]
    assert "within 1 s of start; it delivers" in errors[0]
    assert "ms per render" in errors[0]
    assert "mesh_cell_mm" in errors[0]
    assert "Traceback" not in run.stderr
    assert "ticks" not in run.stdout  # no tick ran, so no run of withheld ticks to report
    assert not list(dataset.rglob("*.parquet"))  # and nothing was recorded
