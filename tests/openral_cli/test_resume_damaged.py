"""``record --resume`` onto a damaged dataset with a camera: one line and exit 2, never an abort.

A MuJoCo twin with a GStreamer camera loads the C++ libraries in the order in which a pyarrow
exception (reading the damaged table) would abort the process with SIGABRT, printing nothing.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from openral_dataset import layout

DEPLOYMENT = """
name: resume_damaged
rate_hz: 30
hal:
  robot_id: so101_follower
  adapter: mujoco_twin
vla:
  id: hello
task:
  instruction: wave hello
sensors:
  - sensor_id: front
    backend: gstreamer
    required: true
    fps: 30
    width: 160
    height: 120
    encoding: bgr8
    max_age_ms: 2000
    backend_params:
      source: testsrc
faults:
  max_consecutive_failures: 1000
safety:
  client: envelope
  mode: clamp
"""


def _record(config: Path, out: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "openral_cli", "record", "--config", str(config), "--dataset-out", str(out),
         "--vcodec", "h264", "--episodes", "1", "--episode-time-s", "0.5", "--reset-time-s", "0", *args],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=180, check=False,
    )  # fmt: skip


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A deployment with the twin and a GStreamer camera, and one episode it recorded."""
    folder = tmp_path_factory.mktemp("resume_damaged")
    config = folder / "deploy.yaml"
    config.write_text(DEPLOYMENT)
    out = folder / "ds"
    proc = _record(config, out)
    assert proc.returncode == 0, proc.stderr
    return config, out


@pytest.mark.gstreamer
@pytest.mark.parametrize("damaged", [layout.TASKS_PATH, "meta/episodes/chunk-000/file-000.parquet"])
def test_a_truncated_table_is_refused_on_one_line_with_exit_2(
    recorded: tuple[Path, Path], tmp_path: Path, damaged: str
) -> None:
    config, dataset = recorded
    root = tmp_path / "ds"
    shutil.copytree(dataset, root)
    table = root / damaged
    table.write_bytes(table.read_bytes()[: table.stat().st_size // 2])

    proc = _record(config, root, "--resume")

    assert proc.returncode == 2, f"exit {proc.returncode}: {proc.stderr}"
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"error: --dataset-out: cannot resume {root}: {damaged}: unreadable"), lines[0]
    assert json.loads((root / layout.INFO_PATH).read_text())["total_episodes"] == 1  # nothing was recorded
