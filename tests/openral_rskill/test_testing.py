"""ScriptedSkill: the fake runner tests drive; it must script, inject and honour the lifecycle."""

from __future__ import annotations

import pytest

from openral_core import Action, ControlMode, ROSSkillError, RSkillState, WorldState
from openral_rskill.testing import ScriptedSkill

NAMES = ["a", "b"]


def world(k: int) -> WorldState:
    return WorldState(stamp_ns=k)


def active(skill: ScriptedSkill) -> ScriptedSkill:
    skill.configure()
    skill.activate()
    return skill


def test_replays_the_script_then_holds() -> None:
    scripted = Action(joint_names=NAMES, targets=[[9.0, 9.0], [8.0, 8.0]])
    skill = active(ScriptedSkill(NAMES, actions=[[1.0, 2.0], scripted], hold=[5.0, 6.0]))
    got = [skill.step(world(k)) for k in range(4)]
    assert got[0].first == [1.0, 2.0]
    assert got[0].joint_names == NAMES
    assert got[0].skill_id == "scripted"
    assert got[1] is scripted
    assert [a.first for a in got[2:]] == [[5.0, 6.0], [5.0, 6.0]]
    assert [w.stamp_ns for w in skill.seen] == [0, 1, 2, 3]


def test_default_hold_is_zeros_in_the_given_control_mode() -> None:
    skill = active(ScriptedSkill(NAMES, skill_id="fake", control_mode=ControlMode.JOINT_VELOCITY))
    action = skill.step(world(0))
    assert action.first == [0.0, 0.0]
    assert action.control_mode is ControlMode.JOINT_VELOCITY
    assert skill.info.skill_id == "fake"


def test_raise_on_latches_after_on_step_ran() -> None:
    ticks: list[int] = []
    boom = RuntimeError("inference crashed")
    skill = active(ScriptedSkill(NAMES, raise_on={2: boom}, on_step=ticks.append))
    skill.step(world(0))
    skill.step(world(1))
    with pytest.raises(ROSSkillError) as info:
        skill.step(world(2))
    assert info.value.__cause__ is boom
    assert ticks == [0, 1, 2]
    assert skill.state is RSkillState.ERROR
    with pytest.raises(ROSSkillError):
        skill.step(world(3))
    assert ticks == [0, 1, 2], "a latched skill is not stepped"
    skill.recover()
    skill.activate()
    skill.step(world(4))
    assert ticks == [0, 1, 2, 3]
    assert len(skill.seen) == 4


def test_honours_the_lifecycle() -> None:
    skill = ScriptedSkill(NAMES)
    with pytest.raises(ROSSkillError, match="UNCONFIGURED"):
        skill.step(world(0))
    active(skill)
    skill.reset()
    skill.shutdown()
    assert skill.calls == ["configure", "activate", "reset", "deactivate", "shutdown"]
    with pytest.raises(ROSSkillError, match="FINALIZED"):
        skill.step(world(0))
    assert skill.seen == []


def test_fail_on_injects_lifecycle_failures() -> None:
    skill = ScriptedSkill(NAMES, fail_on={"activate": OSError("no GPU")})
    skill.configure()
    with pytest.raises(ROSSkillError, match="activate: OSError: no GPU"):
        skill.activate()
    assert skill.state is RSkillState.ERROR


def test_fail_on_rejects_unknown_phases() -> None:
    with pytest.raises(ValueError, match="actvate"):
        ScriptedSkill(NAMES, fail_on={"actvate": OSError()})


def test_script_rows_must_match_the_joint_names() -> None:
    with pytest.raises(ValueError, match="targets"):
        ScriptedSkill(NAMES, actions=[[1.0]])
