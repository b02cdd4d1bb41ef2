"""Shared harness: run a shipped deployment for N ticks, recording what was sent and what was measured."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from openral_core import JointState, RobotEnvironment, RunResult
from openral_runner.factory import build_runner

DEPLOYMENTS = Path(__file__).resolve().parents[2] / "deployments"


@dataclass
class Tracking:
    """One run: its result, the command sent each tick and the joint state measured each tick."""

    result: RunResult
    commanded: np.ndarray
    measured: np.ndarray


@pytest.fixture
def run_tracking() -> Callable[[str, int], Tracking]:
    """Run ``deployments/<name>`` through the factory for ``ticks`` ticks and return what moved."""

    def run(name: str, ticks: int) -> Tracking:
        path = DEPLOYMENTS / name
        runner, skill = build_runner(RobotEnvironment.from_yaml(path), base_dir=path.parent)
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
            result = runner.run(ticks)
        finally:
            runner.deactivate()
            skill.shutdown()
        commanded = np.array([t.sent_action for t in runner.recent_ticks])
        return Tracking(result, commanded, np.array([m.positions for m in measured]))

    return run
