"""RSkillInfo: round trips and field rules."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from openral_core import ControlMode, RSkillInfo, RSkillState

skill_infos = st.builds(
    RSkillInfo,
    skill_id=st.text(min_size=1, max_size=12),
    name=st.text(max_size=12),
    version=st.text(max_size=8),
    license=st.text(max_size=12),
    control_mode=st.sampled_from(list(ControlMode)),
    chunk_size=st.integers(1, 1024),
    description=st.text(max_size=30),
)


@settings(max_examples=60, deadline=None)
@given(skill_infos)
def test_round_trips(info: RSkillInfo) -> None:
    assert RSkillInfo.model_validate_json(info.model_dump_json()) == info
    assert RSkillInfo.model_validate(info.model_dump()) == info


@pytest.mark.parametrize(("field", "value"), [("skill_id", ""), ("chunk_size", 0)])
def test_field_rules(field: str, value: object) -> None:
    with pytest.raises(ValidationError, match=field):
        RSkillInfo.model_validate({"skill_id": "hello", field: value})


def test_defaults() -> None:
    info = RSkillInfo(skill_id="hello")
    assert (info.license, info.chunk_size, info.control_mode) == ("Apache-2.0", 1, ControlMode.JOINT_POSITION)


def test_lifecycle_states_use_ros_managed_node_names() -> None:
    assert [s.value for s in RSkillState] == ["unconfigured", "inactive", "active", "finalized", "error"]
