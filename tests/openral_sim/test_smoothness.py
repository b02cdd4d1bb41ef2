"""Smoothness metrics on trajectories whose jerk, reversals, seam jumps and path length are known by construction."""

from __future__ import annotations

import numpy as np
import pytest

from openral_core import EpisodeResult, EpisodeSmoothness
from openral_sim.env import EnvSpec
from openral_sim.smoothness import ActionGeometry, CommandLog, smoothness, summarize

HZ = 10.0


def absolute(dims: int = 1) -> ActionGeometry:
    return ActionGeometry(control_hz=HZ, delta_dims=(), deadband=np.full(dims, 1e-6))


def delta(dims: int, hold: tuple[int, ...] = ()) -> ActionGeometry:
    spec = EnvSpec(
        state_names=("s",),
        action_names=tuple(f"a{d}" for d in range(dims)),
        action_low=(-1.0,) * dims,
        action_high=(1.0,) * dims,
        action_kind="delta",
        control_hz=HZ,
        hold_dims=hold,
    )
    return ActionGeometry.of(spec)


def metrics(commands: np.ndarray, geometry: ActionGeometry, seams: list[bool] | None = None) -> EpisodeSmoothness:
    commands = np.asarray(commands, dtype=float).reshape(len(commands), -1)
    flags = np.zeros(len(commands), dtype=bool) if seams is None else np.asarray(seams)
    return smoothness(commands, flags, geometry)


def test_a_cubic_in_time_has_its_constant_third_derivative_as_jerk() -> None:
    t = np.arange(30) / HZ
    # x = 2 t³ has jerk 12 everywhere; a constant dimension has none: RMS over both is sqrt(12² / 2).
    commands = np.stack([2 * t**3, np.full_like(t, 0.3)], axis=1)
    result = metrics(commands, absolute(2))
    assert result.jerk_rms == pytest.approx(np.sqrt(144 / 2), rel=1e-6)


def test_a_delta_space_is_measured_on_the_position_its_moves_command() -> None:
    t = np.arange(31) / HZ
    position = 2 * t**3
    moves = np.diff(position)  # what a delta policy sends to follow the cubic
    gripper = 0.5 * t[1:] ** 3  # an absolute dimension in a delta space: jerk 3, not summed
    result = metrics(np.stack([moves, gripper], axis=1), delta(2, hold=(1,)))
    assert result.jerk_rms == pytest.approx(np.sqrt((12**2 + 3**2) / 2), rel=1e-6)
    assert result.reversals_per_s == 0.0  # it only ever moves forward


def test_a_triangle_wave_reverses_at_each_turn() -> None:
    # 0 1 2 3 2 1 0 1 2 3 ...: the velocity changes sign at every peak and trough.
    wave = np.array([3 - abs(3 - (k % 6)) for k in range(24)], dtype=float)
    turns = sum(1 for k in range(1, 23) if (wave[k] - wave[k - 1]) * (wave[k + 1] - wave[k]) < 0)
    assert turns == 7
    result = metrics(wave, absolute())
    assert result.reversals_per_s == pytest.approx(turns / (24 / HZ))
    # Jerk of the triangle: its third difference is ±2 or ±1 at the corners only.
    assert result.jerk_rms is not None
    assert result.jerk_rms > 0


def test_a_square_wave_of_moves_reverses_at_each_edge_and_dimensions_add_up() -> None:
    square = np.array([1.0 if (k // 4) % 2 == 0 else -1.0 for k in range(20)])  # 4 edges
    commands = np.stack([0.01 * square, 0.01 * square], axis=1)
    result = metrics(commands, delta(2))
    assert result.reversals_per_s == pytest.approx(2 * 4 / (20 / HZ))


def test_the_deadband_ignores_noise_and_standing_still() -> None:
    rng = np.random.default_rng(0)
    noisy = 0.5 + rng.normal(0, 1e-9, size=40)
    assert metrics(noisy, absolute()).reversals_per_s == 0.0
    # Forward, stop, forward again is no reversal; forward, stop, back is one.
    assert metrics(np.array([0, 1, 2, 2, 2, 3, 4.0]), absolute()).reversals_per_s == 0.0
    assert metrics(np.array([0, 1, 2, 2, 2, 1, 0.0]), absolute()).reversals_per_s == pytest.approx(1 / (7 / HZ))


def test_seams_are_where_the_row_comes_from_another_chunk_and_held_steps_are_none() -> None:
    log = CommandLog()
    rows = [
        ([0.0, 0.0], 0, False),
        ([0.1, 0.0], 0, False),
        ([0.2, 0.0], 0, False),
        ([0.5, -0.7], 1, False),  # a seam: the new chunk starts 0.3 and 0.7 away -> 0.7
        ([0.6, -0.7], 1, False),
        ([0.6, -0.7], 1, True),  # held: the last target again, no seam
        ([0.9, -0.6], 2, False),  # a seam: 0.3 away from the held step
        ([1.0, -0.6], 2, False),
    ]
    for command, chunk, held in rows:
        log.command(np.array(command), chunk, held=held)
    assert log.seams == [False, False, False, True, False, False, True, False]
    result = log.metrics(absolute(2))
    assert result.seams == 2
    assert result.seam_jump_max == pytest.approx(0.7)
    assert result.seam_jump_p95 == pytest.approx(float(np.percentile([0.7, 0.3], 95)))


def test_without_chunks_every_step_but_the_first_and_the_held_ones_is_a_seam() -> None:
    log = CommandLog()
    for k, held in enumerate([False, False, True, False, False]):
        log.command(np.array([0.1 * k]), None, held=held)
    assert log.seams == [False, True, False, True, True]
    assert log.metrics(absolute()).seams == 3


def test_the_path_length_sums_every_effector_from_the_reset_on() -> None:
    log = CommandLog()
    corners = [(0, 0, 0), (0.1, 0, 0), (0.1, 0.1, 0), (0, 0.1, 0), (0, 0, 0)]  # a 10 cm square
    for x, y, z in corners:
        log.position(np.array([[x, y, z], [2 * x, 2 * y, z]]))  # the second effector draws one twice as big
    for _ in corners[1:]:
        log.command(np.zeros(1), None, held=True)
    assert log.metrics(absolute()).ee_path_length_m == pytest.approx(0.4 + 0.8)
    assert CommandLog().metrics(absolute()).ee_path_length_m is None  # no end effector reported


def test_the_end_effectors_jerk_is_the_third_derivative_of_its_measured_path() -> None:
    log = CommandLog()
    for t in np.arange(12) / HZ:
        # The first effector moves x = 0.5 t³ (jerk 3 m/s³ along x), the second stands still.
        log.position(np.array([[0.5 * t**3, 0.2, 0.1], [0.3, 0.0, 0.0]]))
        log.command(np.zeros(1), None, held=True)
    assert log.metrics(absolute()).ee_jerk_rms == pytest.approx(np.sqrt(3.0**2 / 2))
    short = CommandLog()
    for k in range(3):
        short.position(np.array([0.1 * k, 0.0, 0.0]))
    assert short.metrics(absolute()).ee_jerk_rms is None  # three positions have no third difference


def test_short_episodes_say_what_cannot_be_measured() -> None:
    result = metrics(np.array([0.0, 1.0, 2.0]), absolute())
    assert result.jerk_rms is None  # a third difference needs four commands
    assert result.seam_jump_max is None
    assert result.seams == 0


def test_a_row_gets_each_metrics_mean_and_p95_over_the_episodes_that_have_it() -> None:
    def episode(seed: int, jerk: float | None) -> EpisodeResult:
        smooth = EpisodeSmoothness(commands=10, jerk_rms=jerk, reversals_per_s=float(seed))
        return EpisodeResult(episode_idx=seed, seed=seed, success=True, steps=10, smoothness=smooth)

    episodes = [episode(0, 1.0), episode(1, 3.0), episode(2, None)]
    summary = summarize(episodes)
    assert summary is not None
    assert summary["jerk_rms"] == {"n": 2, "mean": 2.0, "p95": pytest.approx(2.9)}
    assert summary["reversals_per_s"]["mean"] == 1.0
    assert summary["seam_jump_max"] == {"n": 0, "mean": None, "p95": None}
    older = [EpisodeResult(episode_idx=0, seed=0, success=True, steps=10)]
    assert summarize(older) is None
