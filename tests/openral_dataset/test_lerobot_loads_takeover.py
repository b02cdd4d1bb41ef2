"""LeRobot loads a recording with a person's takeover in it, the takeover columns included.

Needs the ``lerobot`` extra (Python 3.12): ``.ci/run`` runs this module again there.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from openral_cli.recording import dataset_entry, recorder_of, with_observers
from openral_core import RobotEnvironment
from openral_runner.factory import build_runner

pytest.importorskip("lerobot", reason="needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)")

from lerobot.datasets.lerobot_dataset import LeRobotDataset


def test_lerobot_loads_the_intervention_rows_of_a_takeover(tmp_path: Path) -> None:
    motion = tmp_path / "leader.json"
    motion.write_text(json.dumps([{"t": t, "positions": {"gripper": 1.0}} for t in (0.0, 1.0)]))
    env = RobotEnvironment.model_validate(
        {
            "rate_hz": 30,
            "hal": {"robot_id": "so101_follower", "adapter": "so10x_follower", "params": {"emulate": True}},
            "vla": {"id": "hello"},
            "takeover": {"skill": "leader_arm", "params": {"emulate": True, "trajectory": str(motion)}},
        }
    )
    out = tmp_path / "ds"
    env = with_observers(env, dataset_entry(out, resume=False, vcodec="h264"), first=True)
    runner, skill = build_runner(env)
    assert runner.takeover is not None
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        runner.episode_start("wave, corrected")
        runner.run(10)
        runner.takeover.request(True)
        runner.run(12)
        runner.takeover.request(False)
        runner.run(8)
        runner.episode_end(success=True)
        recorder = recorder_of(runner.observers)
    finally:
        runner.deactivate()
        skill.shutdown()
    assert recorder.failure is None
    dataset = LeRobotDataset("local/takeover", root=out)
    assert len(dataset) == 30
    human = [bool(dataset[i]["openral.intervention"]) for i in range(len(dataset))]
    assert human == [False] * 10 + [True] * 12 + [False] * 8
    proposals = np.stack([dataset[i]["openral.policy_action"].numpy() for i in range(len(dataset))])
    assert np.isfinite(proposals).all()  # the policy proposed on every tick, the person's included
