"""``Takeover``: who drives the robot (the policy or a person's skill, a leader arm); bumpless switches between them.

A person asks for control from any thread (a key, the web console); the switch happens at the
start of the next tick, never inside one. After every switch the command is limited to one
envelope step per tick from the last command sent, towards the new skill's target, until that
target is within one step: however far the leader arm is from the follower (or the policy's first
action from where the person left the arm), the follower never jumps, whatever the safety
client's mode. Those ticks are flagged (``handover_ramp``) so a recording says so.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence

from openral_core import Action, ControlMode
from openral_rskill.base import RSkillBase


class Takeover:
    """The takeover skill and the state of control; the runner consults it once per tick.

    Args:
        skill: The skill a person drives; the runner configures and activates it at start.
        joint_names: The robot's joints, in the order of ``max_step``.
        max_step: Largest change per tick of each joint while ramping (the envelope's step limit).
        policy_labels: Whether the policy keeps inferring while the person drives, its proposal
            recorded beside the person's action.
    """

    def __init__(
        self,
        skill: RSkillBase,
        *,
        joint_names: Sequence[str],
        max_step: Sequence[float],
        policy_labels: bool = True,
    ) -> None:
        if len(max_step) != len(joint_names) or not all(math.isfinite(s) and s > 0 for s in max_step):
            raise ValueError(f"max_step needs one positive step per joint {list(joint_names)}, got {list(max_step)}")
        self.skill = skill
        self.joint_names = list(joint_names)
        self.max_step = tuple(float(s) for s in max_step)
        self.policy_labels = policy_labels
        self._lock = threading.Lock()
        self._wanted = False
        self._human = False
        self._ramping = False
        self.switches = 0
        """Times control passed, either way."""
        self.human_ticks = 0
        """Ticks the person drove."""

    @property
    def skill_id(self) -> str:
        """The takeover skill's id (what ``active_skill`` says while the person drives)."""
        return self.skill.info.skill_id

    @property
    def human_in_control(self) -> bool:
        """Whether the person drives (as of the last tick's start)."""
        return self._human

    @property
    def requested(self) -> bool:
        """Whether the person should drive from the next tick on (what the last request asked)."""
        return self._wanted

    def request(self, human: bool | None = None) -> None:
        """Ask for control to pass at the next tick: to the person (``True``), the policy (``False``), or toggle.

        Safe from any thread; requests between two ticks collapse into the last one.
        """
        with self._lock:
            self._wanted = (not self._wanted) if human is None else human

    def begin_tick(self) -> bool:
        """Apply a pending request (tick thread, once per tick); ``True`` when control passed now."""
        wanted = self._wanted
        if wanted == self._human:
            if wanted:
                self.human_ticks += 1
            return False
        self._human = wanted
        self._ramping = True
        self.switches += 1
        if wanted:
            self.human_ticks += 1
        return True

    def limit(self, action: Action, reference: Sequence[float] | None) -> tuple[Action, bool]:
        """``action``, limited to one step from ``reference`` per joint while a switch is ramping.

        Returns:
            The action to check and send, and whether it was limited. The ramp ends on the first
            tick whose target is within one step of ``reference`` on every joint; an action for
            other joints or another control mode is left to the safety client (which refuses it).
        """
        if not self._ramping:
            return action, False
        if reference is None or action.control_mode is not ControlMode.JOINT_POSITION:
            return action, False
        if action.joint_names != self.joint_names or len(reference) != len(self.max_step):
            return action, False
        target = action.targets[0]
        limited = list(target)
        clipped = False
        for i, (goal, ref, step) in enumerate(zip(target, reference, self.max_step, strict=True)):
            if not math.isfinite(goal):
                return action, False  # the safety client rejects it, with the reason
            if goal > ref + step:
                limited[i], clipped = ref + step, True
            elif goal < ref - step:
                limited[i], clipped = ref - step, True
        if not clipped:
            self._ramping = False
            return action, False
        ramped = Action.trusted(
            control_mode=action.control_mode,
            joint_names=action.joint_names,
            targets=[limited],
            stamp_ns=action.stamp_ns,
            skill_id=action.skill_id,
        )
        return ramped, True
