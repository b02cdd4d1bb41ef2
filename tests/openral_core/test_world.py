"""JointState, Pose6D, ComponentDiagnostics and WorldState: round trips, alignment and health."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from openral_core import ComponentDiagnostics, FrameEncoding, JointState, Pose6D, SensorFrame, WorldState

PROPERTY = settings(max_examples=60, deadline=None)
finite = st.floats(allow_nan=False, allow_infinity=False)
stamps = st.integers(0, 2**63 - 1)


@st.composite
def joint_states(draw: st.DrawFn) -> JointState:
    names = draw(st.lists(st.text(min_size=1, max_size=8), max_size=7, unique=True))
    n = len(names)
    aligned = st.lists(finite, min_size=n, max_size=n)
    return JointState(
        names=names,
        positions=draw(aligned),
        velocities=draw(st.none() | aligned),
        efforts=draw(st.none() | aligned),
        stamp_ns=draw(stamps),
    )


poses = st.builds(
    Pose6D, x=finite, y=finite, z=finite, roll=finite, pitch=finite, yaw=finite, frame_id=st.text(max_size=10)
)

diagnostics = st.builds(
    ComponentDiagnostics,
    component=st.text(max_size=10),
    age_ms=st.none() | finite,
    max_age_ms=st.none() | finite,
    stale=st.booleans(),
    required=st.booleans(),
    error=st.none() | st.text(max_size=20),
)


@st.composite
def small_frames(draw: st.DrawFn, sensor_id: str) -> SensorFrame:
    width, height = draw(st.integers(1, 4)), draw(st.integers(1, 4))
    encoding = draw(st.sampled_from([FrameEncoding.BGR8, FrameEncoding.MONO8, FrameEncoding.MONO16]))
    size = width * height * {FrameEncoding.BGR8: 3, FrameEncoding.MONO8: 1, FrameEncoding.MONO16: 2}[encoding]
    raw = draw(st.binary(min_size=size, max_size=size))
    data: Any = draw(st.sampled_from([raw, bytearray(raw), np.frombuffer(raw, np.uint8)]))
    return SensorFrame(
        sensor_id=sensor_id, stamp_ns=draw(stamps), width=width, height=height, encoding=encoding, data=data
    )


@st.composite
def world_states(draw: st.DrawFn) -> WorldState:
    sensor_ids = draw(st.lists(st.text(min_size=1, max_size=6), max_size=3, unique=True))
    frames = {sid: draw(small_frames(sid)) for sid in sensor_ids}
    diags = draw(st.dictionaries(st.text(max_size=6), diagnostics, max_size=3))
    return WorldState(
        stamp_ns=draw(stamps),
        joint_state=draw(st.none() | joint_states()),
        ee_pose=draw(st.none() | poses),
        images=draw(st.dictionaries(st.text(max_size=6), st.text(max_size=12), max_size=2)),
        image_frames=draw(st.none() | st.just(frames)),
        diagnostics=diags,
        task=draw(st.none() | st.text(max_size=20)),
    )


@pytest.mark.parametrize(
    ("model", "strategy"),
    [
        (JointState, joint_states()),
        (Pose6D, poses),
        (ComponentDiagnostics, diagnostics),
        (WorldState, world_states()),
    ],
    ids=["JointState", "Pose6D", "ComponentDiagnostics", "WorldState"],
)
@PROPERTY
@given(data=st.data())
def test_round_trips(model: type[Any], strategy: st.SearchStrategy[Any], data: st.DataObject) -> None:
    value = data.draw(strategy)
    assert model.model_validate_json(value.model_dump_json()) == value
    assert model.model_validate(value.model_dump()) == value


def test_world_state_json_carries_frames_as_base64() -> None:
    frame = SensorFrame(sensor_id="cam", stamp_ns=1, width=1, height=1, data=b"\x01\x02\x03")
    ws = WorldState(stamp_ns=2, image_frames={"cam": frame})
    back = WorldState.model_validate_json(ws.model_dump_json())
    assert back.image_frames is not None
    assert back.image_frames["cam"].data == b"\x01\x02\x03"
    assert '"data":"AQID"' in ws.model_dump_json()


def test_world_state_keeps_frame_objects() -> None:
    pixels = np.zeros((2, 2, 3), np.uint8)
    frame = SensorFrame(sensor_id="cam", stamp_ns=1, width=2, height=2, data=pixels)
    ws = WorldState(stamp_ns=2, image_frames={"cam": frame})
    assert ws.image_frames is not None
    assert ws.image_frames["cam"] is frame
    assert np.shares_memory(ws.image_frames["cam"].as_array(), pixels)


# --- JointState -----------------------------------------------------------------------------------


@pytest.mark.parametrize("field", ["positions", "velocities", "efforts"])
def test_joint_state_values_align_with_names(field: str) -> None:
    fields: dict[str, Any] = {"names": ["a", "b"], "positions": [0.0, 1.0], field: [0.0, 1.0, 2.0]}
    with pytest.raises(ValidationError, match=f"{field} has 3 entries for 2 joint names"):
        JointState(**fields)


def test_joint_names_are_unique() -> None:
    with pytest.raises(ValidationError, match="joint names must be unique"):
        JointState(names=["a", "a"], positions=[0.0, 1.0])


def test_position_of_names_a_joint() -> None:
    js = JointState(names=["shoulder", "elbow"], positions=[0.5, -0.25])
    assert js.position_of("elbow") == -0.25
    with pytest.raises(ValueError, match="wrist"):
        js.position_of("wrist")


def test_joint_stamp_is_not_negative() -> None:
    with pytest.raises(ValidationError, match="stamp_ns"):
        JointState(names=[], positions=[], stamp_ns=-1)


def test_unknown_field_is_rejected() -> None:
    with pytest.raises(ValidationError, match="extra"):
        JointState(names=[], positions=[], position=[])  # type: ignore[call-arg]


# --- health ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("stale", "error", "healthy"),
    [(False, None, True), (True, None, False), (False, "bus error", False), (True, "bus error", False)],
)
def test_component_health(stale: bool, error: str | None, healthy: bool) -> None:
    assert ComponentDiagnostics(component="c", stale=stale, error=error).healthy is healthy


def test_stale_components_and_stale_required() -> None:
    ws = WorldState(
        stamp_ns=0,
        diagnostics={
            "joint_state": ComponentDiagnostics(component="joint_state"),
            "front": ComponentDiagnostics(component="front", stale=True),
            "wrist": ComponentDiagnostics(component="wrist", stale=True, required=False),
            "depth": ComponentDiagnostics(component="depth", error="USB reset", required=True),
        },
    )
    assert ws.stale_components == ["front", "wrist", "depth"]
    assert ws.stale_required == ["front", "depth"]


def test_world_state_stamp_is_required() -> None:
    with pytest.raises(ValidationError, match="stamp_ns"):
        WorldState()  # type: ignore[call-arg]
