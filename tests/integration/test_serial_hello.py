"""The emulated SO-101 on its serial bus follows HelloSkill through the full deploy path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("serial", reason="needs the 'serial' extra (pyserial)")

from openral_core import JointState, RobotEnvironment
from openral_runner.factory import build_runner

pytestmark = pytest.mark.slow

DEPLOYMENT = Path(__file__).resolve().parents[2] / "deployments" / "so101_serial_emulated.yaml"
TRACKING_TOLERANCE_RAD = 0.02
"""The emulated servos reach a goal within a tick at this wave's speed; one servo tick is 1.5 mrad."""


def test_emulated_arm_follows_hello() -> None:
    env = RobotEnvironment.from_yaml(DEPLOYMENT)
    runner, skill = build_runner(env, base_dir=DEPLOYMENT.parent)
    measured: list[JointState] = []
    read_state = runner.hal.read_state

    def recording_read() -> JointState:
        state = read_state()
        measured.append(state)
        return state

    runner.hal.read_state = recording_read  # type: ignore[method-assign]
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        result = runner.run(90)
    finally:
        runner.deactivate()
        skill.shutdown()
    assert result.n_ticks == 90
    assert result.withheld_actions == 0
    assert "realtime" in result.metadata
    commanded = np.array([t.sent_action for t in runner.recent_ticks])
    positions = np.array([m.positions for m in measured])
    moving = np.ptp(commanded, axis=0) > 0.05
    assert moving.sum() >= 3
    assert np.all(np.ptp(positions[:, moving], axis=0) > 0.8 * np.ptp(commanded[:, moving], axis=0))
    error = np.abs(positions[1:, moving] - commanded[:-1, moving])
    assert error.max() < TRACKING_TOLERANCE_RAD, f"tracking error {error.max():.4f} rad"
