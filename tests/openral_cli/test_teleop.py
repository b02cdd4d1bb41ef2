"""Teleoperated recording end to end: an emulated leader replays a motion, the emulated follower follows it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from openral_core import ROSConfigError
from openral_dataset import layout
from openral_dataset.check import check_dataset
from openral_hal.feetech.leader import SO10xLeaderArm
from openral_hal.manifests import load_robot_manifest

AMPLITUDE = 0.4
PERIOD_S = 1.0


def _trajectory(path: Path) -> Path:
    """The operator sweeps the shoulder pan back and forth and opens the gripper, looping every second."""
    samples = []
    for k in range(41):
        t = k * PERIOD_S / 40
        phase = 2 * math.pi * t / PERIOD_S
        samples.append(
            {"t": t, "positions": {"shoulder_pan": AMPLITUDE * math.sin(phase), "gripper": 0.5 + 0.3 * math.cos(phase)}}
        )
    path.write_text(json.dumps(samples))
    return path


def test_recording_a_demonstration_commands_the_follower_to_the_leaders_pose(deploy_process, tmp_path: Path) -> None:
    trajectory = _trajectory(tmp_path / "motion.json")
    config = tmp_path / "teleop.yaml"
    config.write_text(
        "name: teleop\nrate_hz: 30\n"
        "hal: {robot_id: so101_follower, adapter: so10x_follower, params: {emulate: true}}\n"
        f"vla: {{id: leader_arm, params: {{emulate: true, trajectory: {trajectory}}}}}\n"
        "task: {instruction: sweep}\n"
        "safety: {client: envelope, mode: clamp}\n"
    )
    out = tmp_path / "ds"
    proc = deploy_process(
        [
            "record",
            "--config",
            str(config),
            "--dataset-out",
            str(out),
            "--vcodec",
            "h264",
            "--episodes",
            "1",
            "--episode-time-s",
            "2.0",
            "--reset-time-s",
            "0",
        ]
    )
    code, _ = proc.finish(timeout=120)
    assert code == 0, proc.stderr
    assert check_dataset(out).problems == []
    table = pq.read_table(layout.data_file(out, 0)).to_pydict()
    requested = np.array(table["openral.requested_action"])
    state = np.array(table["observation.state"])
    sent = np.array(table["action"])
    # The leader's sweep reached the skill: the requested pan covers most of its +-0.4 rad ...
    assert requested[:, 0].max() > 0.7 * AMPLITUDE
    assert requested[:, 0].min() < -0.7 * AMPLITUDE
    # ... the safety envelope let it through: clamped while the follower caught up with the leader's
    # start pose (the gripper starts 0.8 rad away), then passed as it came ...
    assert all(table["openral.action_applied"])
    assert np.abs(sent[0] - requested[0]).max() > 0.1
    passed = np.abs(sent - requested).max(axis=1) < 1e-6
    assert passed.any(), "the envelope never let the leader's pose through"
    caught_up = int(np.argmax(passed))
    assert caught_up < len(sent) // 2
    # A tick delayed by load meets a leader that moved on by the wall clock, a step the envelope may
    # clamp: nearly all, not every, tick after the catch-up passes as it came.
    assert passed[caught_up:].mean() >= 0.9
    # ... and the follower moved with it.
    assert np.ptp(state[:, 0]) > AMPLITUDE


def test_a_leader_refuses_commands_and_a_bad_trajectory_names_the_field(tmp_path: Path) -> None:
    robot = load_robot_manifest("so101_follower")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([{"t": 1.0, "positions": {"shoulder_pan": 0.0}}, {"t": 0.5, "positions": {}}]))
    with pytest.raises(ROSConfigError, match=r"vla\.params\.trajectory: .*times do not increase"):
        SO10xLeaderArm(robot, {"emulate": True, "trajectory": str(bad)})  # read when built: validate reads it too
    leader = SO10xLeaderArm(robot, {"emulate": True})
    leader.connect()
    try:
        assert leader.emulator is not None
        assert not any(leader.emulator.torque().values())  # moved by hand: torque off
        assert len(leader.read_state().positions) == len(robot.joint_names)
        with pytest.raises(ROSConfigError, match="moved by hand"):
            leader.send_action(None)  # type: ignore[arg-type]
    finally:
        leader.disconnect()
