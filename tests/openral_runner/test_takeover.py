"""A person takes control mid-run with an emulated leader arm and gives it back: bumpless, each tick says who drove."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from openral_core import (
    Action,
    ExecutorConfig,
    RobotEnvironment,
    ROSConfigError,
    RSkillInfo,
    RunResult,
    TickResult,
    WithheldReason,
    WorldState,
)
from openral_hal.manifests import load_robot_manifest
from openral_hal.testing import RecordingHAL
from openral_rskill.base import RSkillBase
from openral_rskill.testing import ScriptedSkill
from openral_runner.envelope import EnvelopeSafetyClient
from openral_runner.factory import build_runner
from openral_runner.hardware import HardwareRunner
from openral_runner.takeover import Takeover
from openral_runner.testing import FakeClock
from openral_world_state import WorldStateAggregator

JOINTS = ["a", "b"]


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


def _action(row: list[float]) -> Action:
    return Action(joint_names=JOINTS, targets=[row])


def test_a_switch_ramps_one_step_per_tick_towards_the_new_target_then_passes_it_through() -> None:
    takeover = Takeover(ScriptedSkill(JOINTS), joint_names=JOINTS, max_step=[0.1, 0.2], policy_labels=True)
    assert takeover.limit(_action([5.0, 5.0]), [0.0, 0.0]) == (_action([5.0, 5.0]), False)  # no switch yet
    takeover.request()
    assert not takeover.human_in_control  # applied at the next tick's start, not now
    assert takeover.begin_tick()
    assert takeover.human_in_control
    limited, ramped = takeover.limit(_action([1.0, -0.05]), [0.0, 0.0])
    assert ramped
    assert limited.targets == [[0.1, -0.05]]
    limited, ramped = takeover.limit(_action([0.15, 0.0]), [0.1, -0.05])
    assert not ramped  # within one step on every joint: the ramp is over
    assert limited.targets == [[0.15, 0.0]]
    assert takeover.limit(_action([9.0, 9.0]), [0.15, 0.0]) == (_action([9.0, 9.0]), False)  # the envelope's job now
    takeover.request(False)
    takeover.request(True)  # requests between two ticks collapse into the last
    assert not takeover.begin_tick()
    assert takeover.switches == 1


def test_a_takeover_step_limit_must_name_a_positive_step_per_joint() -> None:
    with pytest.raises(ValueError, match="one positive step per joint"):
        Takeover(ScriptedSkill(JOINTS), joint_names=JOINTS, max_step=[0.1])
    with pytest.raises(ValueError, match="one positive step per joint"):
        Takeover(ScriptedSkill(JOINTS), joint_names=JOINTS, max_step=[0.1, math.nan])


def _leader_motion(path: Path) -> Path:
    """The operator holds the leader away from the follower: the gripper open, the pan turned."""
    samples = [{"t": t, "positions": {"shoulder_pan": 0.5, "gripper": 1.2}} for t in (0.0, 1.0)]
    path.write_text(json.dumps(samples))
    return path


def _deployment(tmp_path: Path, *, safety_mode: str, policy_labels: bool = True) -> RobotEnvironment:
    motion = _leader_motion(tmp_path / "leader.json")
    return RobotEnvironment.model_validate(
        {
            "name": "takeover",
            "rate_hz": 30,
            "hal": {"robot_id": "so101_follower", "adapter": "so10x_follower", "params": {"emulate": True}},
            "vla": {"id": "hello", "params": {"amplitude_rad": 0.2, "frequency_hz": 0.5}},
            "safety": {"client": "envelope", "mode": safety_mode, "max_joint_speed_factor": 0.5},
            "takeover": {
                "skill": "leader_arm",
                "params": {"emulate": True, "trajectory": str(motion)},
                "policy_labels": policy_labels,
            },
        }
    )


_Run = tuple[list[TickResult], tuple[HardwareRunner, RunResult]]


def _run_policy_person_policy(env: RobotEnvironment, ticks: tuple[int, int, int]) -> _Run:
    runner, skill = build_runner(env)
    seen = _Ticks()
    runner.observers.append(seen)
    assert runner.takeover is not None
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        runner.run(max_ticks=ticks[0])
        runner.takeover.request(True)
        runner.run(max_ticks=ticks[1])
        runner.takeover.request(False)
        result = runner.run(max_ticks=ticks[2])
    finally:
        runner.deactivate()
        skill.shutdown()
    return seen.ticks, (runner, result)


def test_policy_then_person_then_policy_is_bumpless_and_every_tick_says_who_drove(tmp_path: Path) -> None:
    # Reject mode: without the ramp, the leader's pose (far from the follower) would be refused,
    # and the person's first ticks would send nothing.
    env = _deployment(tmp_path, safety_mode="reject")
    ticks, (runner, result) = _run_policy_person_policy(env, (20, 40, 30))
    assert len(ticks) == 90
    intervention = [t.intervention for t in ticks]
    assert intervention == [False] * 20 + [True] * 40 + [False] * 30
    assert [t.active_skill for t in ticks] == ["hello"] * 20 + ["leader_arm"] * 40 + ["hello"] * 30
    # Every command passed the envelope, and none moved a joint more than one step.
    assert all(t.action_applied for t in ticks), [t.withheld_reason for t in ticks if not t.action_applied]
    sent = np.array([t.sent_action for t in ticks])
    assert isinstance(runner.safety_client, EnvelopeSafetyClient)
    max_step = np.array(runner.safety_client.max_step)
    assert (np.abs(np.diff(sent, axis=0)) <= max_step + 1e-9).all()
    # The person's pose was reached by a ramp the rows flag, and then followed exactly.
    ramp = [bool(t.handover_ramp) for t in ticks]
    assert ramp[20]
    assert ramp[21]
    human_ramp_end = 20 + ramp[20:60].index(False)
    assert not any(ramp[human_ramp_end:60])
    gripper = load_robot_manifest("so101_follower").joint_names.index("gripper")
    assert sent[59][gripper] == pytest.approx(1.2, abs=1e-3)
    # Back to the policy: it was reset and resumed from where the person left the arm (hello waves
    # about the pose it starts from), moving on from there.
    assert np.abs(sent[60:, gripper] - 1.2).max() < 0.05
    assert np.ptp(sent[60:, 0]) > 1e-3
    # DAgger labels: the policy kept proposing while the person drove.
    assert all(t.policy_action is not None for t in ticks[20:60])
    assert result.metadata["takeover"] == {"skill": "leader_arm", "switches": 2, "human_ticks": 40}


def test_without_policy_labels_the_policy_proposes_nothing_while_the_person_drives(tmp_path: Path) -> None:
    env = _deployment(tmp_path, safety_mode="clamp", policy_labels=False)
    ticks, _ = _run_policy_person_policy(env, (5, 10, 5))
    assert all(t.policy_action is None for t in ticks[5:15])
    assert all(t.policy_action is not None for t in ticks[:5] + ticks[15:])


def test_a_takeover_key_that_the_recording_keys_use_is_refused_with_the_fix(tmp_path: Path) -> None:
    config = tmp_path / "deployment.yaml"
    config.write_text("hal: {robot_id: so101_follower}\nvla: {id: hello}\ntakeover: {skill: leader_arm, key: n}\n")
    with pytest.raises(ROSConfigError, match=r"takeover\.key.*pick another letter"):
        RobotEnvironment.from_yaml(config)


class CountingChunks(RSkillBase):
    """A chunk policy whose every row names the inference it came from: ``[[n, j] for row j]``."""

    def __init__(self) -> None:
        super().__init__()
        self.inferences = 0
        self.resets = 0

    @property
    def info(self) -> RSkillInfo:
        return RSkillInfo(skill_id="counting", chunk_size=8)

    def _on_reset(self) -> None:
        self.resets += 1

    def _step_impl(self, world_state: WorldState) -> Action:
        self.inferences += 1
        return Action(joint_names=JOINTS, targets=[[float(self.inferences), float(j)] for j in range(8)])


def test_a_chunk_policy_given_control_back_starts_a_new_epoch_and_replays_no_older_row() -> None:
    clock = FakeClock()
    policy = CountingChunks()
    person = ScriptedSkill(JOINTS, hold=[-1.0, -1.0], skill_id="person")
    takeover = Takeover(person, joint_names=JOINTS, max_step=[100.0, 100.0], policy_labels=True)
    runner = HardwareRunner(
        hal=RecordingHAL(JOINTS, clock_ns=clock.now_ns),
        skill=policy,
        aggregator=WorldStateAggregator(clock=clock.now_ns),
        rate_hz=30,
        clock=clock,
        thumbnail_hz=0.0,
        executor=ExecutorConfig(margin_ticks=0),
        action_names=JOINTS,
        virtual_delay=lambda request: 2,
        takeover=takeover,
    )
    seen = _Ticks()
    runner.observers.append(seen)
    policy.configure()
    policy.activate()
    runner.activate()
    try:
        runner.run(12)
        takeover.request(True)
        runner.run(10)
        assert person.calls.count("reset") == 1, "the person's turn starts afresh, as the policy's does"
        inferred_before_return = policy.inferences
        resets_before_return = policy.resets
        takeover.request(False)
        runner.run(12)
    finally:
        runner.deactivate()
        policy.shutdown()
    ticks = seen.ticks
    person_ticks = ticks[12:22]
    assert all(t.sent_action == [-1.0, -1.0] for t in person_ticks if t.action_applied)
    assert all(t.policy_action is not None and t.policy_action[0] >= 1 for t in person_ticks)  # it kept inferring
    assert policy.resets == resets_before_return + 1  # reset (a new epoch) the tick control came back
    assert person.calls.count("reset") == 1  # only when control passed to the person
    back = [t for t in ticks[22:] if t.action_applied]
    assert back, "the policy never acted again"
    assert all(t.sent_action is not None and t.sent_action[0] > inferred_before_return for t in back)
    # Until its first new chunk was usable the robot held where the person left it: nothing stale was sent.
    assert [t.withheld_reason for t in ticks[22:24]] == [WithheldReason.AWAITING_CHUNK] * 2
