"""``lerobot_teleop``: LeRobot's own SO-101 leader, on the servo-bus emulator, drives the follower in its radians.

Needs the ``lerobot`` extra (Python 3.12 or newer) for LeRobot's teleoperators and Feetech SDK.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.usefixtures("quick_thread_switches")

LEROBOT_REASON = "needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"

pytest.importorskip("lerobot", reason=LEROBOT_REASON)
pytest.importorskip("scservo_sdk", reason=LEROBOT_REASON)

from click.testing import CliRunner  # noqa: E402

from openral_cli.main import cli  # noqa: E402
from openral_core import RobotEnvironment, RobotManifest, ROSConfigError, ROSSkillError, TickResult  # noqa: E402
from openral_core.world import JointState, WorldState  # noqa: E402
from openral_hal.feetech import protocol as p  # noqa: E402
from openral_hal.feetech.emulator import ServoBusEmulator  # noqa: E402
from openral_hal.feetech.protocol import Register  # noqa: E402
from openral_hal.kinematics import load_site_chain  # noqa: E402
from openral_hal.manifests import load_robot_manifest  # noqa: E402
from openral_rskill.lerobot_teleop import EndEffectorMap, LeRobotTeleopSkill  # noqa: E402
from openral_runner.factory import SKILL_REGISTRY, build_runner  # noqa: E402

MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
BODY_RANGE = (1000, 3100)
GRIPPER_RANGE = (1500, 2700)
TICKS_PER_TURN = 4095  # LeRobot's degrees: (ticks - mid) * 360 / (resolution - 1)


def write_calibration(folder: Path, leader_id: str, motors: tuple[str, ...] = MOTORS) -> Path:
    """A LeRobot calibration file (homing offset 0) for an SO-101 leader's motors."""
    folder.mkdir(parents=True, exist_ok=True)
    calibration = {}
    for servo_id, motor in enumerate(motors, start=1):
        low, high = GRIPPER_RANGE if motor == "gripper" else BODY_RANGE
        calibration[motor] = {"id": servo_id, "drive_mode": 0, "homing_offset": 0, "range_min": low, "range_max": high}
    path = folder / f"{leader_id}.json"
    path.write_text(json.dumps(calibration))
    return path


def expected_radians(robot: RobotManifest, ticks: dict[int, float]) -> list[float]:
    """LeRobot's normalisation of the ticks (degrees body, 0..100 gripper) mapped onto the manifest's joints."""
    out = []
    for servo_id, joint in enumerate(robot.joints, start=1):
        raw = ticks[servo_id]
        if joint.name == "gripper":
            low, high = GRIPPER_RANGE
            percent = (min(max(raw, low), high) - low) / (high - low) * 100
            out.append(joint.lower + percent / 100 * (joint.upper - joint.lower))
        else:
            degrees = (raw - sum(BODY_RANGE) / 2) * 360 / TICKS_PER_TURN
            out.append(math.radians(degrees))
    return out


@pytest.fixture
def robot() -> RobotManifest:
    return load_robot_manifest("so101_follower")


@pytest.fixture
def leader_bus() -> Iterator[ServoBusEmulator]:
    with ServoBusEmulator(range(1, 7)) as emulator:
        yield emulator


def _skill(robot: RobotManifest, params: dict[str, Any]) -> LeRobotTeleopSkill:
    skill = SKILL_REGISTRY["lerobot_teleop"].from_config(params, robot=robot, rate_hz=30.0)
    assert isinstance(skill, LeRobotTeleopSkill)
    return skill


def _leader_skill(robot: RobotManifest, leader_bus: ServoBusEmulator, folder: Path) -> LeRobotTeleopSkill:
    """LeRobot's SO-101 leader on the emulated bus, calibrated by ``folder``/leader.json."""
    return _skill(
        robot, {"type": "so101_leader", "port": leader_bus.port, "id": "leader", "calibration_dir": str(folder)}
    )


def _step(skill: LeRobotTeleopSkill) -> list[float]:
    action = skill.step(WorldState(stamp_ns=0))
    assert action.joint_names == [
        "shoulder_pan",
        "shoulder_lift",
        "elbow_flex",
        "wrist_flex",
        "wrist_roll",
        "gripper",
    ]
    return action.targets[0]


POSE_A = {1: 2450, 2: 1750, 3: 2050, 4: 1000, 5: 3500, 6: 1500}
"""Pan and lift off the middle, the wrist flex at its calibrated end, the roll past it, the jaw closed."""
POSE_B = {1: 1650, 2: 2650, 3: 2850, 4: 2900, 5: 1200, 6: 2100}


def test_the_leaders_pose_is_the_followers_radians_by_lerobots_normalisation(
    robot: RobotManifest, leader_bus: ServoBusEmulator, tmp_path: Path
) -> None:
    write_calibration(tmp_path, "leader")
    skill = _leader_skill(robot, leader_bus, tmp_path)
    skill.configure()
    skill.activate()
    try:
        # The file's ranges were not on the motors yet: activation wrote them, as LeRobot's prompt does on ENTER.
        for servo_id, motor in enumerate(MOTORS, start=1):
            memory = leader_bus.servos[servo_id].memory
            low, high = GRIPPER_RANGE if motor == "gripper" else BODY_RANGE
            assert p.from_u16(memory, Register.MIN_POSITION_LIMIT) == low
            assert p.from_u16(memory, Register.MAX_POSITION_LIMIT) == high
        assert not any(leader_bus.torque().values())  # a leader is moved by hand

        for pose in (POSE_A, POSE_B):
            leader_bus.play([(0.0, pose)])
            assert _step(skill) == pytest.approx(expected_radians(robot, pose), abs=1e-9)

        # The gripper's 0..100 spans the follower jaw's limits: closed, open, and open past the calibrated end.
        jaw = robot.joint("gripper")
        for ticks, radians in ((GRIPPER_RANGE[0], jaw.lower), (GRIPPER_RANGE[1], jaw.upper), (3000, jaw.upper)):
            leader_bus.play([(0.0, {**POSE_A, 6: ticks})])
            assert _step(skill)[5] == pytest.approx(radians, abs=1e-9)
    finally:
        skill.shutdown()
    assert not skill.teleoperator.is_connected


def test_the_actions_follow_the_played_motion(
    robot: RobotManifest, leader_bus: ServoBusEmulator, tmp_path: Path
) -> None:
    write_calibration(tmp_path, "leader")
    skill = _leader_skill(robot, leader_bus, tmp_path)
    end_ticks = {**POSE_A, 4: 1200, 5: 2900, 6: 2600}  # every joint moves, the jaw inside its calibrated range
    start, end = expected_radians(robot, POSE_B), expected_radians(robot, end_ticks)
    skill.configure()
    skill.activate()
    try:
        leader_bus.play([(0.0, POSE_B), (1.0, end_ticks)], loop=False)
        seen = []
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            seen.append(_step(skill))
            if seen[-1] == pytest.approx(end, abs=1e-9):
                break
        assert seen[-1] == pytest.approx(end, abs=1e-9), "the leader's motion never reached its end"
        # Every action is one point of the leader's straight path in ticks: the same fraction on every joint.
        fractions = set()
        for action in seen:
            along = [(a - s) / (e - s) for a, s, e in zip(action, start, end, strict=True)]
            assert max(along) - min(along) < 0.01, along
            assert -0.01 < along[0] < 1.01
            fractions.add(round(along[0], 2))
        assert len(fractions) >= 5  # it moved through the path, not from one end to the other
    finally:
        skill.shutdown()


def test_deactivation_disconnects_and_the_skill_activates_again(
    robot: RobotManifest, leader_bus: ServoBusEmulator, tmp_path: Path
) -> None:
    write_calibration(tmp_path, "leader")
    skill = _leader_skill(robot, leader_bus, tmp_path)
    skill.configure()
    skill.activate()
    assert skill.teleoperator.is_connected
    skill.deactivate()
    assert not skill.teleoperator.is_connected
    leader_bus.play([(0.0, POSE_A)])
    skill.activate()
    try:
        assert _step(skill) == pytest.approx(expected_radians(robot, POSE_A), abs=1e-9)
    finally:
        skill.shutdown()
    assert not skill.teleoperator.is_connected


def test_a_second_skill_on_the_same_leader_is_refused_and_the_first_keeps_reading(
    robot: RobotManifest, leader_bus: ServoBusEmulator, tmp_path: Path
) -> None:
    write_calibration(tmp_path, "leader")
    first, second = _leader_skill(robot, leader_bus, tmp_path), _leader_skill(robot, leader_bus, tmp_path)
    first.configure()
    second.configure()
    first.activate()
    try:
        with pytest.raises(ROSSkillError, match="in use"):
            second.activate()
        leader_bus.play([(0.0, POSE_A)])
        assert _step(first) == pytest.approx(expected_radians(robot, POSE_A), abs=1e-9)
    finally:
        first.shutdown()
        second.shutdown()


def test_a_missing_calibration_file_names_the_file_and_the_command(robot: RobotManifest, tmp_path: Path) -> None:
    params = {"type": "so101_leader", "port": "/dev/ttyACM7", "id": "arm_a", "calibration_dir": str(tmp_path)}
    with pytest.raises(ROSConfigError) as refused:
        _skill(robot, params)
    message = str(refused.value)
    assert f"no LeRobot calibration file {tmp_path / 'arm_a.json'}" in message
    assert (
        "lerobot-calibrate --teleop.type=so101_leader --teleop.port=/dev/ttyACM7 --teleop.id=arm_a "
        f"--teleop.calibration_dir={tmp_path}" in message
    )


def test_a_calibration_file_for_other_motors_is_refused(robot: RobotManifest, tmp_path: Path) -> None:
    path = write_calibration(tmp_path, "arm_b", MOTORS[:5])
    params = {"type": "so101_leader", "port": "/dev/ttyACM7", "id": "arm_b", "calibration_dir": str(tmp_path)}
    with pytest.raises(ROSConfigError, match=rf"calibration file {path} calibrates motors .*'gripper'"):
        _skill(robot, params)


def test_validate_refuses_a_missing_calibration_without_opening_the_port(tmp_path: Path) -> None:
    config = tmp_path / "teleop.yaml"
    port = tmp_path / "no-such-port"  # building must not open it: validate names the calibration, not the port
    config.write_text(
        "name: teleop\nrate_hz: 30\n"
        "hal: {robot_id: so101_follower, adapter: so10x_follower, params: {emulate: true}}\n"
        f"vla: {{id: lerobot_teleop, params: {{type: so101_leader, port: {port}, id: arm_c, "
        f"calibration_dir: {tmp_path}}}}}\n"
    )
    result = CliRunner().invoke(cli, ["validate", str(config)])
    assert result.exit_code != 0
    assert f"vla.params.id: no LeRobot calibration file {tmp_path / 'arm_c.json'}" in result.output
    write_calibration(tmp_path, "arm_c")
    result = CliRunner().invoke(cli, ["validate", str(config)])
    assert result.exit_code == 0, result.output
    assert "skill lerobot_teleop" in result.output


def test_a_wrong_key_names_the_field(robot: RobotManifest) -> None:
    with pytest.raises(ROSConfigError, match=r"vla\.params\.baud: .*allowed keys: calibration_dir, id, .*port"):
        _skill(robot, {"type": "so101_leader", "port": "/dev/ttyACM7", "baud": 1_000_000})


def test_an_unknown_type_lists_the_known_ones(robot: RobotManifest) -> None:
    with pytest.raises(ROSConfigError, match=r"vla\.params\.type: .*'so101_leadr'.*did you mean 'so101_leader'.*"):
        _skill(robot, {"type": "so101_leadr", "port": "/dev/ttyACM7"})
    with pytest.raises(
        ROSConfigError, match=r"vla\.params\.type: .*needs its 'type'.*known: .*koch_leader.*so101_leader"
    ):
        _skill(robot, {"port": "/dev/ttyACM7"})


def test_lerobots_gamepad_builds_as_end_effector_motion_and_needs_a_kinematic_chain(robot: RobotManifest) -> None:
    skill = _skill(robot, {"type": "gamepad", "ee_step_m": 0.01})
    assert isinstance(skill.mapping, EndEffectorMap)
    assert skill.mapping.deltas.step_m == 0.01
    with pytest.raises(ROSConfigError, match=r"'gamepad' teleoperator moves the end effector.*bi_so101_follower"):
        _skill(load_robot_manifest("bi_so101_follower"), {"type": "gamepad"})


PAD_CONFIG = """
from dataclasses import dataclass

from lerobot.teleoperators.config import TeleoperatorConfig


@TeleoperatorConfig.register_subclass("{type_name}")
@dataclass
class ScriptedPadConfig(TeleoperatorConfig):
    delta_x: float = 0.0
    delta_y: float = 0.0
    delta_z: float = 0.0
    gripper: int = 1
    rover: bool = False
"""
PAD = """
from lerobot.teleoperators.teleoperator import Teleoperator

from .config_scripted_pad import ScriptedPadConfig


class ScriptedPad(Teleoperator):
    \"\"\"A gamepad held in one position: LeRobot's gamepad readings (deltas and a gripper action).\"\"\"

    config_class = ScriptedPadConfig
    name = "{type_name}"

    def __init__(self, config):
        super().__init__(config)
        self.config = config
        self.connected = False

    @property
    def action_features(self):
        if self.config.rover:  # a keyboard_rover's readings: velocities of a wheeled base
            return {"linear_velocity": float, "angular_velocity": float}
        return {"dtype": "float32", "shape": (4,), "names": {"delta_x": 0, "delta_y": 1, "delta_z": 2, "gripper": 3}}

    @property
    def feedback_features(self):
        return {}

    @property
    def is_connected(self):
        return self.connected

    def connect(self, calibrate=True):
        self.connected = True

    @property
    def is_calibrated(self):
        return True

    def calibrate(self):
        pass

    def configure(self):
        pass

    def get_action(self):
        c = self.config
        return {"delta_x": c.delta_x, "delta_y": c.delta_y, "delta_z": c.delta_z, "gripper": c.gripper}

    def send_feedback(self, feedback):
        pass

    def disconnect(self):
        self.connected = False
"""


def install_pad(installed_package, type_name: str) -> None:
    """A third-party teleoperator package registering ``type_name`` (LeRobot's registry keeps each name for good)."""
    installed_package(
        f"lerobot_teleoperator_{type_name}",
        "from .config_scripted_pad import ScriptedPadConfig\nfrom .scripted_pad import ScriptedPad\n",
        files={
            "config_scripted_pad.py": PAD_CONFIG.replace("{type_name}", type_name),
            "scripted_pad.py": PAD.replace("{type_name}", type_name),
        },
        importable=True,
    )


def test_a_teleoperator_of_neither_joints_nor_end_effector_deltas_is_refused(
    robot: RobotManifest, installed_package
) -> None:
    install_pad(installed_package, "rover_pad")
    with pytest.raises(ROSConfigError, match=r"'rover_pad' teleoperator gives .*linear_velocity.*not the joint"):
        _skill(robot, {"type": "rover_pad", "rover": True})


def test_end_effector_deltas_move_the_gripper_along_the_asked_axis(robot: RobotManifest, installed_package) -> None:
    install_pad(installed_package, "scripted_pad")
    start = [0.1, -0.4, 0.6, 0.3, 0.0, 0.2]
    measured = WorldState(stamp_ns=0, joint_state=JointState(names=robot.joint_names, positions=start, stamp_ns=0))
    chain = load_site_chain(robot)
    for axis in range(3):
        deltas = {"delta_x": 0.0, "delta_y": 0.0, "delta_z": 0.0} | {("delta_x", "delta_y", "delta_z")[axis]: 1.0}
        skill = _skill(robot, {"type": "scripted_pad", "gripper": 2, "ee_step_m": 0.002, **deltas})
        skill.configure()
        skill.activate()
        rows = [skill.step(measured).targets[0] for _ in range(10)]
        skill.deactivate()
        sites = np.array([chain.position(start), *(chain.position(row) for row in rows)])
        travel = sites[-1] - sites[0]
        # Ten steps of 2 mm along the asked axis, and (almost) nothing along the others.
        assert travel[axis] == pytest.approx(0.02, abs=0.002)
        assert np.abs(np.delete(travel, axis)).max() < 0.002
        # The jaw opens one step per tick (a quarter of its velocity limit at 30 Hz).
        jaw = robot.joints[-1]
        assert rows[-1][-1] == pytest.approx(min(start[-1] + 10 * jaw.velocity_limit / 4 / 30, jaw.upper))


def test_a_new_turn_of_end_effector_teleoperation_starts_from_the_measured_pose(
    robot: RobotManifest, installed_package
) -> None:
    install_pad(installed_package, "turn_pad")
    skill = _skill(robot, {"type": "turn_pad", "delta_z": 1.0, "ee_step_m": 0.002})
    skill.configure()
    skill.activate()
    try:
        first = WorldState(stamp_ns=0, joint_state=JointState(names=robot.joint_names, positions=[0.0] * 6, stamp_ns=0))
        for _ in range(5):
            skill.step(first)
        # Meanwhile the policy moved the arm elsewhere; the person's next turn starts there (the runner resets it).
        moved = [0.3, -0.5, 0.7, 0.2, 0.1, 0.4]
        now = WorldState(stamp_ns=1, joint_state=JointState(names=robot.joint_names, positions=moved, stamp_ns=1))
        skill.reset()
        row = skill.step(now).targets[0]
    finally:
        skill.shutdown()
    assert np.abs(np.subtract(row, moved)).max() < 0.1, "one step from where the robot is, not from the last turn"


def test_a_leader_with_other_joints_than_the_follower_is_refused(robot: RobotManifest) -> None:
    params = {"type": "bi_so_leader", "id": "pair", "left_arm_config": {"port": "a"}, "right_arm_config": {"port": "b"}}
    with pytest.raises(ROSConfigError) as refused:
        _skill(robot, params)
    message = str(refused.value)
    assert "vla.params.type: LeRobot's 'bi_so_leader' teleoperator moves ['left_shoulder_pan'," in message
    assert "does not give 'so101_follower' joint(s) ['shoulder_pan', 'shoulder_lift'," in message


def _bimanual(robot: RobotManifest) -> RobotManifest:
    """Two SO-101 arms as one robot, each joint named with its arm's prefix, as a bimanual LeRobot device keys them."""
    joints = [
        joint.model_copy(update={"name": f"{side}_{joint.name}", "servo_id": None})
        for side in ("left", "right")
        for joint in robot.joints
    ]
    return RobotManifest(robot_id="bi_so101", joints=joints)


def test_a_bimanual_leader_drives_each_arm_by_its_prefix(robot: RobotManifest, tmp_path: Path) -> None:
    both = _bimanual(robot)
    write_calibration(tmp_path, "pair_left")
    write_calibration(tmp_path, "pair_right")
    with ServoBusEmulator(range(1, 7)) as left, ServoBusEmulator(range(1, 7)) as right:
        skill = SKILL_REGISTRY["lerobot_teleop"].from_config(
            {
                "type": "bi_so_leader",
                "id": "pair",
                "calibration_dir": str(tmp_path),
                "left_arm_config": {"port": left.port},
                "right_arm_config": {"port": right.port},
            },
            robot=both,
            rate_hz=30.0,
        )
        left.play([(0.0, POSE_A)])
        right.play([(0.0, POSE_B)])
        skill.configure()
        skill.activate()
        try:
            action = skill.step(WorldState(stamp_ns=0))
        finally:
            skill.shutdown()
    assert action.joint_names == both.joint_names
    assert action.targets[0] == pytest.approx(
        expected_radians(robot, POSE_A) + expected_radians(robot, POSE_B), abs=1e-9
    )


def test_as_a_takeover_skill_its_errors_name_the_takeover_block(tmp_path: Path) -> None:
    config = tmp_path / "takeover.yaml"
    config.write_text(
        "name: takeover\nrate_hz: 30\n"
        "hal: {robot_id: so101_follower, adapter: so10x_follower, params: {emulate: true}}\n"
        "vla: {id: hello}\n"
        f"takeover: {{skill: lerobot_teleop, key: t, params: {{type: so101_leader, port: /dev/ttyACM7, id: arm_d, "
        f"calibration_dir: {tmp_path}}}}}\n"
    )
    result = CliRunner().invoke(cli, ["validate", str(config)])
    assert result.exit_code != 0
    assert f"takeover.params.id: no LeRobot calibration file {tmp_path / 'arm_d.json'}" in result.output
    assert "--teleop.id=arm_d" in result.output
    write_calibration(tmp_path, "arm_d")
    result = CliRunner().invoke(cli, ["validate", str(config)])
    assert result.exit_code == 0, result.output


class _Ticks:
    """Keeps every tick the runner reports."""

    def __init__(self) -> None:
        self.ticks: list[TickResult] = []

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        self.ticks.append(tick)

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        return

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        return

    def close(self) -> None:
        return


def test_a_person_takes_over_with_a_lerobot_leader_and_the_follower_reaches_its_pose(
    robot: RobotManifest, leader_bus: ServoBusEmulator, tmp_path: Path
) -> None:
    write_calibration(tmp_path, "leader")
    leader_bus.play([(0.0, {**POSE_A, 5: 2300})])  # within the follower's roll limits
    env = RobotEnvironment.model_validate(
        {
            "name": "takeover",
            "rate_hz": 30,
            "hal": {"robot_id": "so101_follower", "adapter": "so10x_follower", "params": {"emulate": True}},
            "vla": {"id": "noop"},
            "safety": {"client": "envelope", "mode": "reject"},
            "takeover": {
                "skill": "lerobot_teleop",
                "params": {
                    "type": "so101_leader",
                    "port": leader_bus.port,
                    "id": "leader",
                    "calibration_dir": str(tmp_path),
                },
            },
        }
    )
    runner, skill = build_runner(env)
    seen = _Ticks()
    runner.observers.append(seen)
    assert runner.takeover is not None
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        runner.run(max_ticks=5)
        runner.takeover.request(True)
        runner.run(max_ticks=90)
        runner.takeover.request(False)
        runner.run(max_ticks=5)
    finally:
        runner.deactivate()
        skill.shutdown()
    assert [t.active_skill for t in seen.ticks] == ["noop"] * 5 + ["lerobot_teleop"] * 90 + ["noop"] * 5
    assert all(t.action_applied for t in seen.ticks), [t.withheld_reason for t in seen.ticks if not t.action_applied]
    # The ramp brought the follower to the leader's pose, which it then followed exactly.
    assert not seen.ticks[94].handover_ramp
    assert seen.ticks[94].sent_action == pytest.approx(expected_radians(robot, {**POSE_A, 5: 2300}), abs=1e-9)
    assert not runner.takeover.skill.teleoperator.is_connected
