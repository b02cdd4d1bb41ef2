"""Without LeRobot, a deployment of a LeRobot robot or leader is refused in one line naming the extra (exit 2).

Runs on every Python: a child process blocks ``lerobot``, ``draccus`` and ``torch`` as if they were
not installed, then runs ``openral validate``.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from tests.conftest import WITHOUT_LEROBOT

ROOT = Path(__file__).resolve().parents[2]

VALIDATE_WITHOUT_LEROBOT = (
    WITHOUT_LEROBOT
    + """
from openral_cli.main import main

sys.argv = ["openral", "validate", sys.argv[1]]
main()
"""
)

TELEOP = """\
name: leader
rate_hz: 30
hal: {robot_id: so101_follower, adapter: null}
vla: {id: lerobot_teleop, params: {type: so101_leader, port: /dev/ttyACM1, id: my_leader}}
"""


@pytest.mark.parametrize("deployment", ["so101_lerobot.yaml", "bi_so101_lerobot.yaml", "teleop"])
def test_validate_names_the_lerobot_extra(deployment: str, tmp_path: Path) -> None:
    path = ROOT / "deployments" / deployment
    if deployment == "teleop":
        path = tmp_path / "leader.yaml"
        path.write_text(TELEOP, encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-c", VALIDATE_WITHOUT_LEROBOT, str(path)],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert "needs the Python module 'lerobot', which is not installed" in lines[0]
    assert "lerobot_robot HAL" in lines[0] or "lerobot_teleop" in lines[0]
