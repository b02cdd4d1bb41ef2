"""Fakes for tests of code that drives skills (runners, factories): no weights, no timing noise."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

from openral_core.actions import Action, ControlMode
from openral_core.skills import RSkillInfo
from openral_core.world import WorldState
from openral_rskill.base import RSkillBase

LIFECYCLE_PHASES = ("configure", "activate", "deactivate", "reset", "shutdown")


class ScriptedSkill(RSkillBase):
    """A skill that replays a script, with failures and inference time injected where a test wants them.

    Step ``i`` (counted over the skill's life, across episodes, from 0; a step that raises counts)
    first records the world state in :attr:`seen`, then calls ``on_step(i)`` (a runner test advances
    its fake clock there to simulate inference time), then raises ``raise_on[i]`` if present, and
    otherwise returns ``actions[i]``, or the hold action once the script has run out.

    It is a real :class:`RSkillBase`: stepping outside ``ACTIVE`` fails and an injected exception sets
    the error latch.

    Args:
        joint_names: Joint names every generated action carries.
        actions: The script: ``Action`` objects, or rows of targets (one value per joint name).
        hold: Targets of the hold action; zeros when ``None``.
        raise_on: Step index -> exception raised by that step.
        on_step: Called with the step index at the start of every step.
        fail_on: Lifecycle phase (``configure``, ``activate``, ``deactivate``, ``reset``, ``shutdown``)
            -> exception its hook raises, every time it runs.
        skill_id: Id in :attr:`info` and on generated actions.
        control_mode: Control mode in :attr:`info` and on generated actions.
    """

    def __init__(
        self,
        joint_names: Sequence[str],
        *,
        actions: Sequence[Action | Sequence[float]] = (),
        hold: Sequence[float] | None = None,
        raise_on: Mapping[int, Exception] | None = None,
        on_step: Callable[[int], None] | None = None,
        fail_on: Mapping[str, Exception] | None = None,
        skill_id: str = "scripted",
        control_mode: ControlMode = ControlMode.JOINT_POSITION,
    ) -> None:
        super().__init__()
        self.joint_names = list(joint_names)
        self._info = RSkillInfo(skill_id=skill_id, name="Scripted skill", control_mode=control_mode)
        self.actions = [a if isinstance(a, Action) else self._action(a) for a in actions]
        hold_row = [0.0] * len(self.joint_names) if hold is None else list(hold)
        self.hold_action = self._action(hold_row)
        self.raise_on = dict(raise_on or {})
        self.on_step = on_step
        unknown = set(fail_on or {}) - set(LIFECYCLE_PHASES)
        if unknown:
            raise ValueError(f"fail_on has unknown phases {sorted(unknown)}; known: {', '.join(LIFECYCLE_PHASES)}")
        self.fail_on = dict(fail_on or {})
        self.seen: list[WorldState] = []
        self.calls: list[str] = []
        """Lifecycle hooks in the order they ran (``configure``, ``activate``, ...)."""
        self.steps_taken = 0

    @property
    def info(self) -> RSkillInfo:
        """Identity of this fake."""
        return self._info

    def _action(self, row: Sequence[float]) -> Action:
        return Action(
            control_mode=self._info.control_mode,
            joint_names=self.joint_names,
            targets=[list(row)],
            skill_id=self._info.skill_id,
        )

    def _hook(self, phase: str) -> None:
        self.calls.append(phase)
        exc = self.fail_on.get(phase)
        if exc is not None:
            raise exc

    def _on_configure(self) -> None:
        self._hook("configure")

    def _on_activate(self) -> None:
        self._hook("activate")

    def _on_deactivate(self) -> None:
        self._hook("deactivate")

    def _on_reset(self) -> None:
        self._hook("reset")

    def _on_shutdown(self) -> None:
        self._hook("shutdown")

    def _step_impl(self, world_state: WorldState) -> Action:
        index = self.steps_taken
        self.steps_taken = index + 1
        self.seen.append(world_state)
        if self.on_step is not None:
            self.on_step(index)
        exc = self.raise_on.get(index)
        if exc is not None:
            raise exc
        return self.actions[index] if index < len(self.actions) else self.hold_action
