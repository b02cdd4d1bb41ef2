"""``ActionBoxSafetyClient``: a simulated robot's actions kept inside its environment's action space.

The same contract as on hardware: non-finite values and wrong dimensions are rejected (the tick
is withheld and counted), and values outside the bounds are clamped, the replacement recorded as
the action sent.
"""

from __future__ import annotations

import math

from openral_core import Action, ROSSafetyViolation, SafetyEnvelope
from openral_runner.safety import SafetyClient
from openral_sim.env import EnvSpec


class ActionBoxSafetyClient(SafetyClient):
    """Checks row 0 of each action against the env's action names and bounds."""

    def __init__(self, spec: EnvSpec) -> None:
        self.envelope = SafetyEnvelope()
        self.spec = spec
        self._names = list(spec.action_names)

    def check_action(self, action: Action) -> Action | None:
        if action.joint_names != self._names:
            raise ROSSafetyViolation(
                f"action names {action.joint_names} are not the environment's {self._names}",
                check_name="action_names",
            )
        row = action.first
        if not all(math.isfinite(v) for v in row):
            raise ROSSafetyViolation(f"non-finite action {row}", check_name="finite")
        clamped = [
            min(max(v, lo), hi) for v, lo, hi in zip(row, self.spec.action_low, self.spec.action_high, strict=True)
        ]
        if clamped == row and action.horizon == 1:
            return None
        return action.model_copy(update={"targets": [clamped]})
