"""``metaworld_expert``: MetaWorld's own scripted policy for a task, reading the privileged 39-d ``obs``.

MetaWorld ships one hand-written policy per v3 task (``metaworld.policies``); this skill runs the
one for ``params.task`` on the observation the ``metaworld`` environment exposes as privileged
value ``obs``, and emits its ``[dx, dy, dz, grip]`` clipped to the action box. The policies are
stateless, so episodes need no reset.

The policies warn ("Constant(s) may be too high") whenever a proportional response exceeds the
action box, which is most steps and harmless (the action is clipped); that one warning is
silenced around the policy call.
"""

from __future__ import annotations

import difflib
import warnings
from collections.abc import Callable, Mapping
from typing import Any, Self

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from openral_core import (
    Action,
    ControlMode,
    RobotManifest,
    ROSConfigError,
    ROSDependencyMissing,
    RSkillInfo,
    WorldState,
)
from openral_rskill.base import validate_params
from openral_sim.skills._base import ActionSpaceSkill, privileged

try:
    from metaworld.policies import ENV_POLICY_MAP
    from metaworld.policies.policy import Policy
except ImportError as exc:
    # Importing metaworld imports mujoco (its package imports every task).
    raise ROSDependencyMissing(
        exc.name or "metaworld", extra="sim", needed_for="the MetaWorld scripted experts"
    ) from exc

POLICIES: Mapping[str, Callable[[], Policy]] = ENV_POLICY_MAP
"""MetaWorld's scripted policy for each task id."""

_LARGE_RESPONSE_WARNING = r"Constant\(s\) may be too high"


class MetaWorldExpertParams(BaseModel):
    """``params`` of ``metaworld_expert``."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    task: str = Field(min_length=1, description="The MetaWorld task the policy solves, as the scene's env_id.")


class MetaWorldExpert(ActionSpaceSkill):
    """MetaWorld's scripted policy for one task; simulation only (it reads privileged ``obs``)."""

    INFO = RSkillInfo(
        skill_id="metaworld_expert",
        name="MetaWorld scripted expert",
        version="1.0.0",
        description="MetaWorld's hand-written policy for a v3 task (privileged state).",
    )

    def __init__(self, robot: RobotManifest, task: str) -> None:
        super().__init__(robot, ControlMode.EE_DELTA)
        policy_class = POLICIES.get(task)
        if policy_class is None:
            close = difflib.get_close_matches(task, list(POLICIES), n=3)
            raise ROSConfigError(
                f"MetaWorld has no scripted policy for task {task!r}",
                field="params.task",
                hint=f"did you mean {' or '.join(repr(c) for c in close)}?"
                if close
                else f"choose from {sorted(POLICIES)}",
            )
        self.task = task
        self._policy: Policy = policy_class()

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        return cls(robot, validate_params(MetaWorldExpertParams, params, skill_id="metaworld_expert").task)

    @property
    def info(self) -> RSkillInfo:
        return self.INFO

    def _step_impl(self, world_state: WorldState) -> Action:
        obs = privileged(world_state, "obs")
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=_LARGE_RESPONSE_WARNING, category=UserWarning)
            action = np.asarray(self._policy.get_action(obs), dtype=np.float64)
        return self.emit(np.clip(action, self.low, self.high), world_state)
