"""What the simulation skills share: the action space they were built for, and one way to emit an action."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from openral_core import Action, ControlMode, RobotManifest, WorldState
from openral_rskill.base import RSkillBase


class ActionSpaceSkill(RSkillBase):
    """A skill that emits one row in the order and bounds of ``robot``'s entries (an env's action space)."""

    def __init__(self, robot: RobotManifest, control_mode: ControlMode) -> None:
        super().__init__()
        self.robot = robot
        self.names = robot.joint_names
        self.low = np.array([j.lower for j in robot.joints])
        self.high = np.array([j.upper for j in robot.joints])
        self._mode = control_mode

    def emit(self, values: Sequence[float] | np.ndarray, world_state: WorldState) -> Action:
        return Action(
            control_mode=self._mode,
            joint_names=self.names,
            targets=[[float(v) for v in values]],
            stamp_ns=world_state.stamp_ns,
            skill_id=self.info.skill_id,
        )


def privileged(world_state: WorldState, name: str) -> np.ndarray:
    """A privileged value of a simulated world state.

    Raises:
        ValueError: The world state is not from a simulator (a robot has no privileged state).
    """
    if world_state.privileged is None:
        raise ValueError("this skill reads the simulator's privileged state: it runs in simulation only")
    return np.asarray(world_state.privileged.get(name), dtype=np.float64)
