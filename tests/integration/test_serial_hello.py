"""The emulated SO-101 on its serial bus follows HelloSkill through the full deploy path."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("serial", reason="needs the 'serial' extra (pyserial)")

pytestmark = pytest.mark.slow

TRACKING_TOLERANCE_RAD = 0.02
"""The emulated servos reach a goal within a tick at this wave's speed; one servo tick is 1.5 mrad."""


def test_emulated_arm_follows_hello(run_tracking) -> None:
    run = run_tracking("so101_serial_emulated.yaml", 90)
    assert run.result.n_ticks == 90
    assert run.result.withheld_actions == 0
    assert "realtime" in run.result.metadata
    moving = np.ptp(run.commanded, axis=0) > 0.05
    assert moving.sum() >= 3
    assert np.all(np.ptp(run.measured[:, moving], axis=0) > 0.8 * np.ptp(run.commanded[:, moving], axis=0))
    error = np.abs(run.measured[1:, moving] - run.commanded[:-1, moving])
    assert error.max() < TRACKING_TOLERANCE_RAD, f"tracking error {error.max():.4f} rad"
