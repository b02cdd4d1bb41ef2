"""``hello``: a smooth, bounded joint-space wave around the pose the robot starts from.

The first skill to run on a new robot: it proves the loop closes (state in, commands out) while
moving little, slowly and never outside the joint limits. For joint ``j``::

    target_j(t) = c_j + A_j * ramp(t) * sin(2π f t + j_index * phase_step)

``t = steps / rate_hz`` counts ticks, not wall time, so the trajectory is deterministic and a late
tick delays the wave instead of making it jump. ``c`` is the pose measured on the first step after
``activate``/``reset`` (clamped into the limits); ``ramp`` rises smoothly from 0 to 1 over ``ramp_s``
so the first command equals the start pose. ``A_j`` is the configured amplitude shrunk, once per
episode, so that the wave stays ``limit_margin`` inside ``[lower, upper]`` and its speed, including
the ramp's contribution, stays below ``max_speed_fraction`` of the joint's velocity limit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core.actions import Action, ControlMode
from openral_core.errors import ROSConfigError
from openral_core.robot import JointKind, RobotManifest
from openral_core.skills import RSkillInfo
from openral_core.world import WorldState
from openral_rskill.base import RSkillBase, validate_params
from openral_rskill.chunks import ChunkRequest
from openral_rskill.pose import clamp_to_limits, measured_pose

SKILL_ID = "hello"

# ramp(s) = 6s^5 - 15s^4 + 10s^3 (smootherstep): zero speed and acceleration at both ends;
# its steepest slope is 15/8 per ramp duration.
_RAMP_MAX_SLOPE = 15.0 / 8.0


class HelloParams(BaseModel):
    """``vla.params`` of the ``hello`` skill.

    Attributes:
        amplitude_rad: Wave amplitude (joint units: rad for revolute joints); shrunk per joint to fit
            the limits and the speed bound.
        frequency_hz: Wave frequency; must stay below half the tick rate.
        ramp_s: Time for the amplitude to grow from 0 to full, so the wave starts without a jump. The
            speed bound covers the ramp too, so a very short ramp shrinks the amplitude.
        joints: Joints that wave; default all revolute joints (plus grippers when ``gripper: wave``).
            Every other joint holds its start value.
        phase_step_rad: Phase offset between successive waving joints, so the arm ripples.
        gripper: ``hold`` keeps gripper joints at their start value; ``wave`` moves them too.
        max_speed_fraction: Largest commanded speed as a fraction of each joint's velocity limit.
        limit_margin: Distance kept from each joint limit (joint units).
        chunk_size: Rows per step. Above 1 the skill is a chunking policy (run by the chunk
            executor, or served remotely): row ``j`` is the wave ``j`` ticks after the observation,
            timed by the observation's stamp rather than by counting steps.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    amplitude_rad: float = Field(default=0.2, ge=0.0)
    frequency_hz: float = Field(default=0.25, gt=0.0)
    ramp_s: float = Field(default=1.0, gt=0.0)
    joints: list[str] | None = None
    phase_step_rad: float = math.pi / 4
    gripper: Literal["hold", "wave"] = "hold"
    max_speed_fraction: float = Field(default=0.5, gt=0.0, le=1.0)
    limit_margin: float = Field(default=0.05, ge=0.0)
    chunk_size: int = Field(default=1, ge=1, le=1000)


class HelloSkill(RSkillBase):
    """Joint-position wave around the start pose; see the module docstring for the trajectory.

    Args:
        robot: The robot it commands; every action names all of its joints, in manifest order.
        rate_hz: Tick rate ``step`` is called at (defines the time axis).
        params: Wave parameters (defaults when ``None``).

    Raises:
        ROSConfigError: ``joints`` names an unknown joint, repeats one, or names a gripper while
            ``gripper`` is ``hold``; ``frequency_hz`` is at or above half of ``rate_hz``.
    """

    INFO = RSkillInfo(
        skill_id=SKILL_ID,
        name="Hello wave",
        version="1.0.0",
        license="Apache-2.0",
        control_mode=ControlMode.JOINT_POSITION,
        chunk_size=1,
        description="Smooth, bounded joint-space wave around the start pose.",
    )

    def __init__(self, robot: RobotManifest, *, rate_hz: float, params: HelloParams | None = None) -> None:
        super().__init__()
        self.robot = robot
        self.params = params if params is not None else HelloParams()
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ROSConfigError(f"must be a positive number, got {rate_hz}", field="rate_hz")
        self.rate_hz = float(rate_hz)
        if self.params.frequency_hz >= self.rate_hz / 2:
            raise ROSConfigError(
                f"{self.params.frequency_hz} Hz cannot be sampled at rate_hz {self.rate_hz:g}",
                field="vla.params.frequency_hz",
                hint=f"use a frequency below {self.rate_hz / 2:g} Hz, or raise rate_hz",
            )
        self._names = robot.joint_names
        moving = _moving_joints(robot, self.params)
        step = self.params.phase_step_rad
        self._phases = [moving.index(n) * step if n in moving else 0.0 for n in self._names]
        self._moving = [n in moving for n in self._names]
        self._omega = 2.0 * math.pi * self.params.frequency_hz
        self._ramp_s = self.params.ramp_s
        # Speed of A·r(t)·sin(ωt+φ) is A·|r'·sin + r·ω·cos| <= A·sqrt(r'max² + ω²).
        self._speed_gain = math.hypot(self._omega, _RAMP_MAX_SLOPE / self._ramp_s)
        self._centre: list[float] | None = None
        self._amplitudes: list[float] = [0.0] * len(self._names)
        self._k = 0
        self._first_stamp_ns: int | None = None
        self._info = self.INFO.model_copy(update={"chunk_size": self.params.chunk_size})

    def _row(self, centre: list[float], t: float) -> list[float]:
        ramp = _ramp(t, self._ramp_s)
        wt = self._omega * t
        sin = math.sin
        return [c + a * ramp * sin(wt + p) for c, a, p in zip(centre, self._amplitudes, self._phases, strict=True)]

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        """Build from ``vla.params`` (see :class:`HelloParams`)."""
        return cls(robot, rate_hz=rate_hz, params=validate_params(HelloParams, params, skill_id=SKILL_ID))

    @property
    def info(self) -> RSkillInfo:
        """Identity of the ``hello`` skill (its chunk size from the parameters)."""
        return self._info

    @property
    def start_pose(self) -> list[float] | None:
        """The latched wave centre (manifest order), ``None`` until the episode's first step."""
        return None if self._centre is None else list(self._centre)

    @property
    def amplitudes(self) -> list[float]:
        """Per-joint amplitude in effect this episode, after shrinking (0 for holding joints)."""
        return list(self._amplitudes)

    def _on_activate(self) -> None:
        self._new_episode()

    def _on_reset(self) -> None:
        self._new_episode()

    def _new_episode(self) -> None:
        self._centre = None
        self._amplitudes = [0.0] * len(self._names)
        self._k = 0
        self._first_stamp_ns = None

    def _latch_centre(self, world_state: WorldState) -> list[float]:
        centre = clamp_to_limits(measured_pose(world_state, self._names), self.robot)
        amplitude = self.params.amplitude_rad
        margin = self.params.limit_margin
        speed_cap = self.params.max_speed_fraction / self._speed_gain
        amplitudes = []
        for c, spec, moving in zip(centre, self.robot.joints, self._moving, strict=True):
            if not moving:
                amplitudes.append(0.0)
                continue
            room = min(c - (spec.lower + margin), (spec.upper - margin) - c)
            # A few ulps of slack so that rounding in c + a·sin(...) cannot cross the bound.
            room -= 4.0 * math.ulp(max(abs(spec.lower), abs(spec.upper), 1.0))
            amplitudes.append(max(0.0, min(amplitude, room, spec.velocity_limit * speed_cap)))
        self._amplitudes = amplitudes
        self._centre = centre
        return centre

    def _rows(self, world_state: WorldState) -> list[list[float]]:
        centre = self._centre if self._centre is not None else self._latch_centre(world_state)
        if self.params.chunk_size == 1:
            k = self._k
            self._k = k + 1
            return [self._row(centre, k / self.rate_hz)]
        # A chunk: timed by the observation, row j for j ticks later.
        if self._first_stamp_ns is None:
            self._first_stamp_ns = world_state.stamp_ns
        t0 = (world_state.stamp_ns - self._first_stamp_ns) / 1e9
        return [self._row(centre, t0 + j / self.rate_hz) for j in range(self.params.chunk_size)]

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        """The chunk for the request's observation as one array (no ``Action`` built for the executor)."""
        return np.array(self._rows(request.world), dtype=np.float64)

    def _step_impl(self, world_state: WorldState) -> Action:
        return Action(
            control_mode=ControlMode.JOINT_POSITION,
            joint_names=self._names,
            targets=self._rows(world_state),
            stamp_ns=world_state.stamp_ns,
            skill_id=SKILL_ID,
        )


def _ramp(t: float, ramp_s: float) -> float:
    """0 → 1 over ``ramp_s`` with zero slope and curvature at both ends (smootherstep)."""
    if t >= ramp_s:
        return 1.0
    s = max(0.0, t) / ramp_s
    return s * s * s * (s * (6.0 * s - 15.0) + 10.0)


def _moving_joints(robot: RobotManifest, params: HelloParams) -> list[str]:
    grippers = {j.name for j in robot.joints if j.kind is JointKind.GRIPPER}
    if params.joints is None:
        return [j.name for j in robot.joints if j.name not in grippers or params.gripper == "wave"]
    known = robot.joint_names
    unknown = [n for n in params.joints if n not in known]
    if unknown:
        raise ROSConfigError(
            f"unknown joints {unknown} for robot '{robot.robot_id}'; its joints are {', '.join(known)}",
            field="vla.params.joints",
        )
    if len(set(params.joints)) != len(params.joints):
        raise ROSConfigError(f"repeats a joint: {params.joints}", field="vla.params.joints")
    held_grippers = [n for n in params.joints if n in grippers and params.gripper == "hold"]
    if held_grippers:
        raise ROSConfigError(
            f"{held_grippers} are grippers, which hold while 'gripper' is 'hold'",
            field="vla.params.joints",
            hint="remove them from joints, or set gripper: wave",
        )
    return list(params.joints)
