"""Smoothness of what reached the robot: each metric defined once, computed per episode, summarised per row.

An episode's record is the command sent to the env at each step, after the safety envelope; a
step whose action was withheld sends the env's hold action, which reaches the robot too, so it
counts. The metrics read the *commanded motion* ``x``, in the env's action units: the command
itself on an absolute dimension, and on a delta dimension (a space whose commands are moves,
:attr:`~openral_sim.env.EnvSpec.action_kind` ``delta``, less its ``hold_dims``) the running sum of
the moves, the position they command. With ``dt = 1 / control_hz``:

* ``jerk_rms`` (action units/s³): the third finite difference of ``x`` over ``dt³``, RMS over
  every step and dimension; ``None`` with fewer than four commands.
* ``seam_jump_max`` / ``seam_jump_p95`` (action units): at each *seam*, the largest absolute
  change of the command over its dimensions (per-dimension maximum, so dimensions of different
  units are never added); their maximum and 95th percentile over the episode's seams, ``None``
  without a seam. A seam is a step whose row came from another chunk than the step before's (a
  held step is none: it repeats the last target); for a skill without chunks each step's action
  is its own, so every step but a held one is a seam. The first step of an episode has no step
  before it.
* ``reversals_per_s`` (1/s): sign changes of each dimension's velocity ``x[t+1] − x[t]``, summed
  over dimensions, per simulated second of the episode (``commands × dt``). A velocity within
  the *deadband*, :data:`DEADBAND_OF_RANGE` of the dimension's action range per step, is no
  direction (numeric noise and standing still reverse nothing); a reversal is a change of sign
  between two velocities outside it.
* ``ee_path_length_m`` (metres): the distance the end effector travelled, from its position
  after the reset through each step's, summed over effectors; ``None`` where the env reports no
  end effector (:class:`~openral_sim.env.EndEffectorSensing`).
* ``ee_jerk_rms`` (m/s³): the jerk of the end effector's *measured* path, as the simulator moved
  it: the third finite difference of each effector's position over ``dt³``, its Euclidean norm,
  RMS over steps and effectors; ``None`` with fewer than four positions or no end effector. Unlike
  the metrics of the commanded motion it is in physical units whatever the action space (joint
  targets, end-effector moves), so two policies driving one robot through different action
  representations compare on it.

Across a row's episodes, each metric's mean and p95 (over the episodes that have a value).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from openral_core import EpisodeResult, EpisodeSmoothness
from openral_sim.env import EnvSpec

DEADBAND_OF_RANGE: Final = 1e-4
"""A velocity below this share of a dimension's action range per step has no direction."""

METRICS: Final = {
    "jerk_rms": ("jerk RMS", "action units/s³"),
    "seam_jump_max": ("largest seam jump", "action units"),
    "seam_jump_p95": ("seam jump p95", "action units"),
    "reversals_per_s": ("reversals", "per s"),
    "ee_path_length_m": ("end-effector path", "m"),
    "ee_jerk_rms": ("end-effector jerk RMS", "m/s³"),
}
"""The per-episode metrics a row summarises and a comparison pairs (name: how a person reads it, its unit)."""


@dataclass(frozen=True)
class ActionGeometry:
    """What the metrics need to know of an env's action space: its rate, its delta dimensions, its deadband."""

    control_hz: float
    delta_dims: tuple[int, ...]
    deadband: np.ndarray
    """Per dimension, in action units per step."""

    @classmethod
    def of(cls, spec: EnvSpec) -> ActionGeometry:
        """The geometry of ``spec``'s action space."""
        dims = len(spec.action_names)
        delta = () if spec.action_kind == "absolute" else tuple(d for d in range(dims) if d not in spec.hold_dims)
        span = np.asarray(spec.action_high, dtype=np.float64) - np.asarray(spec.action_low, dtype=np.float64)
        return cls(control_hz=spec.control_hz, delta_dims=delta, deadband=DEADBAND_OF_RANGE * np.abs(span))


class CommandLog:
    """One episode's commands as sent, which of them start at a seam, and the end effector's positions.

    Appends only (a row per step): bounded by the episode, cheap on the tick.
    """

    __slots__ = ("_last_chunk", "commands", "positions", "seams")

    def __init__(self) -> None:
        self.commands: list[np.ndarray] = []
        self.seams: list[bool] = []
        self.positions: list[np.ndarray] = []
        self._last_chunk: int | None = None

    def command(self, command: np.ndarray, chunk: int | None, *, held: bool) -> None:
        """Record the step's command: ``chunk`` is the id of the chunk its row came from (``None``: no chunk)."""
        seam = False
        if not held:
            seam = bool(self.commands) and (chunk is None or chunk != self._last_chunk)
            self._last_chunk = chunk
        self.commands.append(command)
        self.seams.append(seam)

    def position(self, position: np.ndarray) -> None:
        """Record where the end effector(s) are now (``(3,)`` or ``(effectors, 3)``, metres)."""
        self.positions.append(position)

    def metrics(self, geometry: ActionGeometry) -> EpisodeSmoothness:
        """The episode's metrics (module docstring)."""
        dims = len(geometry.deadband)
        commands = np.asarray(self.commands, dtype=np.float64).reshape(len(self.commands), dims)
        positions = np.asarray(self.positions, dtype=np.float64) if len(self.positions) > 1 else None
        return smoothness(commands, np.asarray(self.seams, dtype=bool), geometry, positions)


def smoothness(
    commands: np.ndarray, seams: np.ndarray, geometry: ActionGeometry, positions: np.ndarray | None = None
) -> EpisodeSmoothness:
    """The metrics of ``commands`` (``(steps, dims)``) with their ``seams`` flags and the effector's ``positions``."""
    jumps = seam_jumps(commands, seams)
    return EpisodeSmoothness(
        commands=len(commands),
        jerk_rms=jerk_rms(commands, geometry),
        seams=len(jumps),
        seam_jump_max=float(jumps.max()) if len(jumps) else None,
        seam_jump_p95=float(np.percentile(jumps, 95)) if len(jumps) else None,
        reversals_per_s=reversals_per_s(commands, geometry),
        ee_path_length_m=None if positions is None else path_length(positions),
        ee_jerk_rms=None if positions is None else path_jerk_rms(positions, geometry.control_hz),
    )


def commanded_motion(commands: np.ndarray, geometry: ActionGeometry) -> np.ndarray:
    """``x``: the commands, with each delta dimension's moves summed into the position they command."""
    motion = np.array(commands, dtype=np.float64)
    if geometry.delta_dims and len(motion):
        dims = list(geometry.delta_dims)
        motion[:, dims] = np.cumsum(motion[:, dims], axis=0)
    return motion


def jerk_rms(commands: np.ndarray, geometry: ActionGeometry) -> float | None:
    """RMS of the commanded motion's third finite difference over ``dt³`` (action units/s³)."""
    if len(commands) < 4:
        return None
    jerk = np.diff(commanded_motion(commands, geometry), n=3, axis=0) * geometry.control_hz**3
    return float(np.sqrt(np.mean(jerk**2)))


def seam_jumps(commands: np.ndarray, seams: np.ndarray) -> np.ndarray:
    """At each seam (never the first step), the largest absolute change of the command over its dimensions."""
    steps = np.flatnonzero(seams[1:]) + 1
    if not len(steps):
        return np.zeros(0)
    return np.asarray(np.abs(commands[steps] - commands[steps - 1]).max(axis=1), dtype=np.float64)


def reversals_per_s(commands: np.ndarray, geometry: ActionGeometry) -> float | None:
    """Sign changes of each dimension's velocity outside the deadband, summed, per simulated second."""
    if len(commands) < 3:
        return None
    velocity = np.diff(commanded_motion(commands, geometry), axis=0)
    signs = np.where(np.abs(velocity) > geometry.deadband, np.sign(velocity), 0.0)
    reversals = 0
    for column in signs.T:
        moving = column[column != 0]
        reversals += int(np.count_nonzero(moving[1:] != moving[:-1]))
    return reversals / (len(commands) / geometry.control_hz)


def path_length(positions: np.ndarray) -> float:
    """The distance travelled through ``positions`` (``(steps, [effectors,] 3)``), summed over effectors."""
    steps = np.diff(_by_effector(positions), axis=0)
    return float(np.linalg.norm(steps, axis=-1).sum())


def path_jerk_rms(positions: np.ndarray, control_hz: float) -> float | None:
    """RMS over steps and effectors of the norm of ``positions``' third finite difference over ``dt³`` (m/s³)."""
    if len(positions) < 4:
        return None
    jerk = np.diff(_by_effector(positions), n=3, axis=0) * control_hz**3
    return float(np.sqrt(np.mean(np.sum(jerk**2, axis=-1))))


def _by_effector(positions: np.ndarray) -> np.ndarray:
    """``(steps, 3)`` or ``(steps, effectors, 3)`` positions as ``(steps, effectors, 3)``."""
    return positions.reshape(len(positions), -1, 3)


def summarize(episodes: Sequence[EpisodeResult]) -> dict[str, Any] | None:
    """Each metric's mean and p95 over the episodes that have it; ``None`` when no episode recorded smoothness."""
    recorded = [e.smoothness for e in episodes if e.smoothness is not None]
    if not recorded:
        return None
    summary: dict[str, Any] = {"n_episodes": len(recorded)}
    for name in METRICS:
        values = [v for v in (getattr(s, name) for s in recorded) if v is not None]
        summary[name] = {
            "n": len(values),
            "mean": float(np.mean(values)) if values else None,
            "p95": float(np.percentile(values, 95)) if values else None,
        }
    return summary
