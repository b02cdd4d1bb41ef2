"""How a policy's action rows become targets that stay right however late its chunk arrives.

A chunk computed from the observation of tick ``k`` is executed from a later tick. Absolute
targets can simply be indexed by tick (row ``j`` is for tick ``k + j``); relative rows cannot, so
they are *anchored* at tick ``k`` first: turned into absolute targets using the state the policy
saw, and turned back into the command the robot takes at the tick each row is sent.

* ``absolute``: rows are targets (joint or end-effector); nothing to do.
* ``relative_to_state``: row ``j`` is an offset from the state at the observation's tick.
* ``delta_ee``: row ``j`` moves the end effector by ``scale * row[j]`` from where row ``j - 1``
  left it (a simulator's ``[dx, dy, dz, grasp]``); anchored at the end-effector position seen at
  tick ``k``, sent as the move from the position measured at the tick of sending.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import StrEnum
from typing import Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import WorldState


class ActionRepresentation(StrEnum):
    """What a policy's action rows mean."""

    ABSOLUTE = "absolute"
    """Targets (joint positions or end-effector poses): row j is where to be at tick k + j."""
    RELATIVE_TO_STATE = "relative_to_state"
    """Offsets from the measured state at the observation's tick."""
    DELTA_EE = "delta_ee"
    """Successive end-effector moves (scaled), with some dimensions absolute (a gripper)."""
    UNANCHORED = "unanchored"
    """Relative rows whose reference cannot be measured: executed from the chunk's start (stale start)."""


class Anchor(Protocol):
    """Turns a chunk's rows into absolute targets at the observation's tick, and a target into a command."""

    def to_targets(self, rows: np.ndarray, observed: WorldState) -> np.ndarray:
        """Absolute targets for ``rows`` (shape ``(n, dims)``), from the world state the policy saw."""
        ...

    def to_command(self, target: np.ndarray, now: WorldState) -> np.ndarray:
        """The command that moves the robot towards ``target`` from the state of this tick."""
        ...


class AbsoluteAnchor:
    """Rows are already targets."""

    def to_targets(self, rows: np.ndarray, observed: WorldState) -> np.ndarray:
        return rows

    def to_command(self, target: np.ndarray, now: WorldState) -> np.ndarray:
        return target


class UnanchoredRows:
    """Relative rows whose reference cannot be measured: each chunk runs from its first row when it arrives."""

    def to_targets(self, rows: np.ndarray, observed: WorldState) -> np.ndarray:
        return rows

    def to_command(self, target: np.ndarray, now: WorldState) -> np.ndarray:
        return target


class StateOffsetAnchor:
    """Rows are offsets from the measured joints named ``names`` at the observation's tick."""

    def __init__(self, names: Sequence[str]) -> None:
        self.names = list(names)

    def to_targets(self, rows: np.ndarray, observed: WorldState) -> np.ndarray:
        joints = observed.joint_state
        if joints is None:
            raise ValueError("a relative_to_state chunk needs the measured joints of its observation")
        by_name = dict(zip(joints.names, joints.positions, strict=True))
        return np.asarray(rows + np.array([by_name[name] for name in self.names]))

    def to_command(self, target: np.ndarray, now: WorldState) -> np.ndarray:
        return target


class EndEffectorDeltaAnchor:
    """Rows move the end effector by ``scale`` per unit from the previous row's end.

    Args:
        position_key: Privileged value holding the moved point's position (``grasp_pos`` in the
            SO-101 simulation).
        scale: Metres per unit of action.
        position_dims: The three action dimensions that move the point; the others are absolute.
        limit: Largest command per dimension (the action space's bound).
    """

    def __init__(
        self, position_key: str, scale: float, position_dims: Sequence[int] = (0, 1, 2), limit: float = 1.0
    ) -> None:
        self.position_key = position_key
        self.scale = scale
        self.dims = list(position_dims)
        self.limit = limit

    def _position(self, world: WorldState) -> np.ndarray:
        if world.privileged is None:
            raise ValueError(f"a delta_ee chunk is anchored at privileged {self.position_key!r}: simulation only")
        return np.asarray(world.privileged.get(self.position_key), dtype=np.float64)

    def to_targets(self, rows: np.ndarray, observed: WorldState) -> np.ndarray:
        targets = np.array(rows, dtype=np.float64, copy=True)
        path = self._position(observed) + self.scale * np.cumsum(rows[:, self.dims], axis=0)
        targets[:, self.dims] = path
        return targets

    def to_command(self, target: np.ndarray, now: WorldState) -> np.ndarray:
        command = np.array(target, dtype=np.float64, copy=True)
        move = (target[self.dims] - self._position(now)) / self.scale
        command[self.dims] = np.clip(move, -self.limit, self.limit)
        return command


class AnchorSpec(BaseModel):
    """An anchor as data, so a policy served elsewhere is anchored on the robot exactly as it would be locally."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    representation: ActionRepresentation = ActionRepresentation.ABSOLUTE
    names: list[str] = Field(default_factory=list, description="relative_to_state: the joints offset.")
    position_key: str | None = Field(default=None, description="delta_ee: the privileged position moved.")
    scale: float = Field(default=1.0, gt=0, description="delta_ee: metres per unit.")
    position_dims: list[int] = Field(default_factory=lambda: [0, 1, 2])
    limit: float = Field(default=1.0, gt=0)

    @classmethod
    def of(cls, anchor: Anchor) -> AnchorSpec:
        """The spec of one of the anchors of this module.

        Raises:
            TypeError: Another kind of anchor (it cannot be described, so it cannot be served).
        """
        if isinstance(anchor, StateOffsetAnchor):
            return cls(representation=ActionRepresentation.RELATIVE_TO_STATE, names=anchor.names)
        if isinstance(anchor, EndEffectorDeltaAnchor):
            return cls(
                representation=ActionRepresentation.DELTA_EE,
                position_key=anchor.position_key,
                scale=anchor.scale,
                position_dims=anchor.dims,
                limit=anchor.limit,
            )
        if isinstance(anchor, UnanchoredRows):
            return cls(representation=ActionRepresentation.UNANCHORED)
        if isinstance(anchor, AbsoluteAnchor):
            return cls()
        raise TypeError(f"{type(anchor).__name__} cannot be described as data")

    def build(self) -> Anchor:
        """The anchor this spec describes."""
        if self.representation is ActionRepresentation.RELATIVE_TO_STATE:
            return StateOffsetAnchor(self.names)
        if self.representation is ActionRepresentation.DELTA_EE and self.position_key is not None:
            return EndEffectorDeltaAnchor(self.position_key, self.scale, self.position_dims, self.limit)
        if self.representation in (ActionRepresentation.DELTA_EE, ActionRepresentation.UNANCHORED):
            return UnanchoredRows()
        return AbsoluteAnchor()
