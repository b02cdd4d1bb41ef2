"""``openral record`` with LeRobot's own devices at both ends: an SO-101 leader drives an SO-101 follower.

The leader (``lerobot_teleop``, ``so101_leader``) and the follower (``lerobot_robot``,
``so101_follower``) are LeRobot's drivers, each on an emulated Feetech bus; the dataset they give
passes openral's check and loads in LeRobot.

Needs the ``lerobot`` extra (Python 3.12 or newer) for LeRobot's teleoperators and Feetech SDK.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

pytest.importorskip("lerobot", reason=LEROBOT_REASON)
pytest.importorskip("scservo_sdk", reason=LEROBOT_REASON)

from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402

from openral_dataset import layout  # noqa: E402
from openral_dataset.check import check_dataset  # noqa: E402
from openral_hal.feetech.emulator import ServoBusEmulator  # noqa: E402
from openral_hal.manifests import load_robot_manifest  # noqa: E402

MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
BODY_RANGE = (1000, 3100)
GRIPPER_RANGE = (1500, 2700)
MID = sum(BODY_RANGE) / 2
PAN = (1650, 2450)
JAW = (1700, 2500)
"""The operator sweeps the pan and opens the jaw together, and back, every second; the other joints hold."""
HELD = {2: 2250, 3: 1850, 4: 2050, 5: 2450}


def _calibration(folder: Path, arm_id: str) -> None:
    calibration = {}
    for servo_id, motor in enumerate(MOTORS, start=1):
        low, high = GRIPPER_RANGE if motor == "gripper" else BODY_RANGE
        calibration[motor] = {"id": servo_id, "drive_mode": 0, "homing_offset": 0, "range_min": low, "range_max": high}
    (folder / f"{arm_id}.json").write_text(json.dumps(calibration))


def _radians(ticks: float) -> float:
    """A body joint's ticks in radians: LeRobot's degrees about the calibrated middle."""
    return math.radians((ticks - MID) * 360 / 4095)


def test_recording_with_a_lerobot_leader_records_the_leaders_motion(deploy_process, tmp_path: Path) -> None:
    _calibration(tmp_path, "leader")
    _calibration(tmp_path, "follower")
    jaw = load_robot_manifest("so101_follower").joint("gripper")
    jaw_radians = [
        jaw.lower + (t - GRIPPER_RANGE[0]) / (GRIPPER_RANGE[1] - GRIPPER_RANGE[0]) * (jaw.upper - jaw.lower)
        for t in JAW
    ]
    out = tmp_path / "ds"
    with ServoBusEmulator(range(1, 7)) as leader, ServoBusEmulator(range(1, 7)) as follower:
        leader.play(
            [
                (0.0, {1: PAN[0], 6: JAW[0], **HELD}),
                (0.5, {1: PAN[1], 6: JAW[1], **HELD}),
                (1.0, {1: PAN[0], 6: JAW[0], **HELD}),
            ]
        )
        config = tmp_path / "teleop.yaml"
        config.write_text(
            "name: lerobot_teleop\nrate_hz: 30\n"
            f"hal: {{robot_id: so101_follower, adapter: lerobot_robot, params: {{type: so101_follower, "
            f"port: {follower.port}, id: follower, calibration_dir: {tmp_path}}}}}\n"
            f"vla: {{id: lerobot_teleop, params: {{type: so101_leader, port: {leader.port}, id: leader, "
            f"calibration_dir: {tmp_path}}}}}\n"
            "task: {instruction: sweep}\n"
            "safety: {client: envelope, mode: clamp}\n"
        )
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
        code, _ = proc.finish(timeout=300)
        follower_torque = follower.torque()
    assert code == 0, proc.stderr
    assert not any(follower_torque.values()), "the follower ends limp"
    assert check_dataset(out).problems == []
    table = pq.read_table(layout.data_file(out, 0)).to_pydict()
    requested = np.array(table["openral.requested_action"])
    state = np.array(table["observation.state"])
    assert len(requested) >= 50
    # The held joints are the leader's ticks in the follower's radians, every tick ...
    for servo_id, ticks in HELD.items():
        assert requested[:, servo_id - 1] == pytest.approx(_radians(ticks), abs=1e-6)  # stored as float32
    # ... the pan and the jaw move together along the leader's path, end to end ...
    pan = (requested[:, 0] - _radians(PAN[0])) / (_radians(PAN[1]) - _radians(PAN[0]))
    opening = (requested[:, 5] - jaw_radians[0]) / (jaw_radians[1] - jaw_radians[0])
    assert np.abs(pan - opening).max() < 0.01
    assert pan.min() > -0.01
    assert pan.max() < 1.01
    assert pan.min() < 0.2
    assert pan.max() > 0.8
    # ... and the follower went with them.
    assert np.ptp(state[:, 0]) > 0.5 * (_radians(PAN[1]) - _radians(PAN[0]))
    # LeRobot reads it as its own: every frame, the joints named, the actions as recorded.
    dataset = LeRobotDataset("local/lerobot_teleop", root=out)
    assert dataset.num_frames == len(requested)
    assert dataset.meta.features["action"]["names"] == list(MOTORS)
    np.testing.assert_allclose(dataset[len(requested) - 1]["action"].numpy(), np.array(table["action"])[-1])
