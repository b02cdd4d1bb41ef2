"""Shared fixtures: an SO-arm-like robot manifest and a world-state builder (no HAL needed)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import pytest

from openral_core import JointKind, JointSpec, JointState, RobotManifest, WorldState

WorldFactory = Callable[..., WorldState]


def so_arm() -> RobotManifest:
    """Five revolute joints and a gripper, with SO-101-like limits."""
    return RobotManifest(
        robot_id="test_arm",
        joints=[
            JointSpec(name="shoulder_pan", lower=-1.9, upper=1.9, velocity_limit=3.0),
            JointSpec(name="shoulder_lift", lower=-1.7, upper=1.7, velocity_limit=3.0),
            JointSpec(name="elbow_flex", lower=-1.6, upper=1.6, velocity_limit=3.0),
            JointSpec(name="wrist_flex", lower=-1.6, upper=1.6, velocity_limit=4.0),
            JointSpec(name="wrist_roll", lower=-2.7, upper=2.7, velocity_limit=4.0),
            JointSpec(name="gripper", kind=JointKind.GRIPPER, lower=0.0, upper=1.0, velocity_limit=2.0),
        ],
    )


def world(
    names: Sequence[str] | None = None, positions: Sequence[float] | None = None, *, stamp_ns: int = 1_000
) -> WorldState:
    """A world state carrying one joint state (or none when ``names`` is ``None``)."""
    if names is None:
        return WorldState(stamp_ns=stamp_ns)
    assert positions is not None
    return WorldState(
        stamp_ns=stamp_ns,
        joint_state=JointState(names=list(names), positions=list(positions), stamp_ns=stamp_ns),
    )


@pytest.fixture(scope="session")
def robot() -> RobotManifest:
    return so_arm()


@pytest.fixture(scope="session")
def make_world() -> WorldFactory:
    return world
