"""``openral deploy`` with a takeover skill: a key hands control to the emulated leader and back; the rows say so."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from openral_cli.main import cli
from openral_core import RobotEnvironment, SafetyEnvelope
from openral_dataset import layout
from openral_dataset.check import check_dataset
from openral_hal.manifests import load_robot_manifest

SPEED_FACTOR = 0.5


def _deployment(tmp_path: Path) -> Path:
    motion = tmp_path / "leader.json"
    motion.write_text(json.dumps([{"t": t, "positions": {"shoulder_pan": 0.6, "gripper": 1.0}} for t in (0.0, 1.0)]))
    config = tmp_path / "takeover.yaml"
    config.write_text(
        "name: takeover\nrate_hz: 30\n"
        "hal: {robot_id: so101_follower, adapter: so10x_follower, params: {emulate: true}}\n"
        "vla: {id: hello, params: {amplitude_rad: 0.2, frequency_hz: 0.5}}\n"
        f"safety: {{client: envelope, mode: clamp, max_joint_speed_factor: {SPEED_FACTOR}}}\n"
        f"takeover: {{skill: leader_arm, params: {{emulate: true, trajectory: {motion}}}, key: t}}\n"
    )
    RobotEnvironment.from_yaml(config)
    return config


def test_the_takeover_key_hands_control_to_the_leader_and_back_and_the_rows_say_which_were_human(
    deploy_process, tmp_path: Path
) -> None:
    out = tmp_path / "ds"
    proc = deploy_process(
        ["deploy", "--config", str(_deployment(tmp_path)), "--dataset-out", str(out), "--vcodec", "h264",
         "--duration", "30"],
        keys=True,
    )  # fmt: skip
    proc.wait_for("running")
    proc.press("t")
    proc.wait_for("to=leader_arm")
    proc.press("t")
    proc.wait_for("to=hello")
    proc.press("q")  # an orderly stop, as Ctrl-C
    code, stdout = proc.finish(timeout=60)
    assert code == 0, proc.stderr
    assert "stop_requested" in stdout
    assert check_dataset(out).problems == []
    table = pq.read_table(layout.data_file(out, 0)).to_pydict()
    human = np.array(table["openral.intervention"])
    first, last = int(np.argmax(human)), len(human) - 1 - int(np.argmax(human[::-1]))
    assert human.any()
    assert human[first : last + 1].all(), "the person's ticks are one block"
    assert not human[last + 1 :].all(), "control came back"
    assert table["openral.active_skill"] == ["leader_arm" if h else "hello" for h in human]
    # No commanded step, at either switch or anywhere else, exceeds the envelope's step limit.
    robot = load_robot_manifest("so101_follower")
    envelope = SafetyEnvelope(max_joint_speed_factor=SPEED_FACTOR)
    max_step = np.array([j.velocity_limit * envelope.max_joint_speed_factor / 30 for j in robot.joints])
    action = np.array(table["action"])
    assert (np.abs(np.diff(action, axis=0)) <= max_step + 1e-6).all()
    # The leader was far from the follower: the first person's ticks ramped, and the rows say so.
    assert table["openral.handover_ramp"][first]
    proposals = np.array(table["openral.policy_action"])
    assert np.isfinite(proposals).all(), "the policy proposed an action on every tick, the person's included"


def _takeover_config(tmp_path: Path, leader: str, *, speed_factor: str = str(SPEED_FACTOR)) -> Path:
    config = tmp_path / "takeover.yaml"
    config.write_text(
        "name: takeover\nrate_hz: 30\n"
        "hal: {robot_id: so101_follower, adapter: so10x_follower, params: {emulate: true}}\n"
        "vla: {id: hello, params: {amplitude_rad: 0.2, frequency_hz: 0.5}}\n"
        f"safety: {{client: envelope, mode: clamp, max_joint_speed_factor: {speed_factor}}}\n"
        f"takeover: {{skill: leader_arm, params: {{{leader}}}, key: t}}\n"
    )
    return config


@pytest.mark.parametrize(
    ("content", "says"),
    [
        (None, "file not found"),
        ("this is no JSON", "is not valid JSON"),
        ('{"t": 0}', "Input should be a valid array"),
        ("[" * 100_000 + "]" * 100_000, "is nested too deeply"),
        ('[{"t": 0, "positions": {"gripper": 1e400}}]', "number 1e400 is too large"),
        ('[{"t": 0, "positions": {"gripper": 1}}, {"t": 0, "positions": {"gripper": 0}}]', "times do not increase"),
        ('[{"t": 0, "positions": {"jaw": 1}}]', "joint(s) ['jaw']"),
    ],
    ids=["missing", "garbage", "not-a-list", "nested", "infinite", "time-still", "unknown-joint"],
)
@pytest.mark.parametrize("command", ["validate", "deploy"])
def test_a_leader_trajectory_that_cannot_be_replayed_is_a_config_error_naming_the_takeover_block(
    tmp_path: Path, content: str | None, says: str, command: str
) -> None:
    motion = tmp_path / "leader.json"
    if content is not None:
        motion.write_text(content)
    config = _takeover_config(tmp_path, f"emulate: true, trajectory: {motion}")
    args = [command, str(config)] if command == "validate" else [command, "--config", str(config), "--duration", "5"]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 2, out.output
    (line,) = out.output.strip().splitlines()
    assert line.startswith("error: takeover.params.trajectory"), line
    assert str(motion) in line
    assert says in line


def test_a_leader_calibration_error_names_the_takeover_block(tmp_path: Path) -> None:
    config = _takeover_config(tmp_path, f"port: /dev/null, calibration: {tmp_path / 'leader_cal.json'}")
    out = CliRunner().invoke(cli, ["validate", str(config)])
    assert out.exit_code == 2, out.output
    assert out.output.startswith("error: takeover.params.calibration: file not found"), out.output


@pytest.mark.parametrize("command", ["validate", "deploy"])
def test_a_speed_factor_whose_step_underflows_is_a_config_error_naming_it(tmp_path: Path, command: str) -> None:
    motion = tmp_path / "leader.json"
    motion.write_text(json.dumps([{"t": t, "positions": {"gripper": 1.0}} for t in (0.0, 1.0)]))
    config = _takeover_config(tmp_path, f"emulate: true, trajectory: {motion}", speed_factor="4.9e-324")
    args = [command, str(config)] if command == "validate" else [command, "--config", str(config), "--duration", "5"]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 2, out.output
    (line,) = out.output.strip().splitlines()
    assert line.startswith("error: safety.max_joint_speed_factor: "), line
    assert "raise it" in line
