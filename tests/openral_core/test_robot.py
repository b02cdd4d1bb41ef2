"""Robot manifests: JointSpec limits, unique joints, lookups and round trips."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from openral_core import JointKind, JointSpec, ModelRef, RobotManifest

PROPERTY = settings(max_examples=60, deadline=None)
finite = st.floats(min_value=-1e6, max_value=1e6)
positive = st.floats(min_value=1e-6, max_value=1e6)


@st.composite
def joint_specs(draw: st.DrawFn, name: str | None = None) -> JointSpec:
    lower = draw(finite)
    return JointSpec(
        name=name or draw(st.text(min_size=1, max_size=8)),
        kind=draw(st.sampled_from(list(JointKind))),
        lower=lower,
        upper=lower + draw(st.floats(min_value=1e-3, max_value=1e3)),
        velocity_limit=draw(positive),
        effort_limit=draw(st.none() | positive),
        servo_id=draw(st.none() | st.integers(0, 253)),
    )


model_refs = st.builds(
    ModelRef,
    package=st.text(max_size=10),
    path=st.text(max_size=20),
    ee_site=st.none() | st.text(max_size=8),
    cameras=st.lists(st.text(max_size=8), max_size=3),
)


@st.composite
def manifests(draw: st.DrawFn) -> RobotManifest:
    names = draw(st.lists(st.text(min_size=1, max_size=8), min_size=1, max_size=7, unique=True))
    return RobotManifest(
        robot_id=draw(st.text(min_size=1, max_size=10)),
        name=draw(st.text(max_size=10)),
        description=draw(st.text(max_size=30)),
        joints=[draw(joint_specs(n)) for n in names],
        base_frame=draw(st.text(max_size=10)),
        mujoco=draw(st.none() | model_refs),
        source=draw(st.text(max_size=10)),
    )


@PROPERTY
@given(joint_specs())
def test_joint_spec_round_trips(spec: JointSpec) -> None:
    assert JointSpec.model_validate_json(spec.model_dump_json()) == spec
    assert JointSpec.model_validate(spec.model_dump()) == spec


@PROPERTY
@given(manifests())
def test_manifest_round_trips(manifest: RobotManifest) -> None:
    assert RobotManifest.model_validate_json(manifest.model_dump_json()) == manifest
    assert RobotManifest.model_validate(manifest.model_dump()) == manifest


def _joint(name: str = "shoulder_pan", **overrides: object) -> JointSpec:
    fields: dict[str, object] = {"name": name, "lower": -1.0, "upper": 1.0, "velocity_limit": 3.0}
    fields.update(overrides)
    return JointSpec.model_validate(fields)


@pytest.mark.parametrize("upper", [-1.0, -2.0])
def test_lower_must_be_below_upper(upper: float) -> None:
    with pytest.raises(ValidationError, match=r"joint 'shoulder_pan': lower \(-1\.0\) must be below upper"):
        _joint(upper=upper)


@pytest.mark.parametrize(
    ("field", "value"),
    [("velocity_limit", 0.0), ("effort_limit", -1.0), ("servo_id", 254), ("servo_id", -1), ("name", "")],
)
def test_joint_field_ranges(field: str, value: object) -> None:
    with pytest.raises(ValidationError, match=field):
        _joint(**{field: value})


def test_manifest_rejects_repeated_joint_names() -> None:
    with pytest.raises(ValidationError, match="robot 'arm' repeats a joint name"):
        RobotManifest(robot_id="arm", joints=[_joint("a"), _joint("a")])


def test_manifest_needs_a_joint() -> None:
    with pytest.raises(ValidationError, match="joints"):
        RobotManifest(robot_id="arm", joints=[])


def test_joint_names_keep_manifest_order_and_lookup_by_name() -> None:
    manifest = RobotManifest(robot_id="arm", joints=[_joint("wrist"), _joint("elbow", kind=JointKind.GRIPPER)])
    assert manifest.joint_names == ["wrist", "elbow"]
    assert manifest.joint("elbow").kind is JointKind.GRIPPER
    with pytest.raises(KeyError, match="knee"):
        manifest.joint("knee")
