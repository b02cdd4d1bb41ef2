"""``EnvelopeSafetyClient``: joint limits, step limits and finiteness, from the robot manifest.

Checks row 0 of each action (the row the HAL applies) and, when it is allowed, replaces the
action with exactly that checked row so nothing unchecked can reach the robot.
"""

from __future__ import annotations

import math

from openral_core import (
    Action,
    ControlMode,
    JointState,
    RobotManifest,
    ROSSafetyViolation,
    SafetyConfig,
    SafetyEnvelope,
    SafetyMode,
)


class EnvelopeSafetyClient:
    """Keeps joint-position commands inside the robot's limits and speed envelope.

    * Non-finite values and wrong joint sets are always rejected.
    * Out-of-range positions are clipped (``clamp``) or rejected (``reject``).
    * The step from the reference (the last command sent, or the measured position before
      the first one) is limited to ``velocity_limit × max_joint_speed_factor × period``.

    Args:
        robot: Joint limits and velocity limits.
        rate_hz: Tick rate, to turn velocity limits into a per-tick step.
        mode: ``clamp`` or ``reject``.
        envelope: Further limits; ``max_joint_speed_factor`` scales the step limit.
    """

    def __init__(
        self,
        robot: RobotManifest,
        *,
        rate_hz: float,
        mode: SafetyMode = SafetyMode.CLAMP,
        envelope: SafetyEnvelope | None = None,
    ) -> None:
        self.envelope = envelope or SafetyEnvelope()
        self.mode = mode
        self.joint_names = robot.joint_names
        self._lower = [j.lower for j in robot.joints]
        self._upper = [j.upper for j in robot.joints]
        factor = self.envelope.max_joint_speed_factor
        self._max_step = [j.velocity_limit * factor / rate_hz for j in robot.joints]
        self._reference: list[float] | None = None

    @classmethod
    def from_config(cls, config: SafetyConfig, *, robot: RobotManifest, rate_hz: float) -> EnvelopeSafetyClient:
        """Plugin constructor from the deployment's ``safety`` block."""
        envelope = SafetyEnvelope(
            max_joint_speed_factor=config.max_joint_speed_factor,
            workspace_min=config.workspace_min,
            workspace_max=config.workspace_max,
        )
        return cls(robot, rate_hz=rate_hz, mode=config.mode, envelope=envelope)

    def observe_state(self, state: JointState) -> None:
        """Use the measured position as the step reference until a command has been sent."""
        if self._reference is None and state.names == self.joint_names:
            self._reference = list(state.positions)

    def commit(self, action: Action) -> None:
        """Record the command the HAL accepted: the reference for the next step limit."""
        self._reference = list(action.targets[0])

    def check_action(self, action: Action) -> Action | None:
        """Return the checked single-row action to send, or raise ``ROSSafetyViolation``."""
        if action.control_mode is not ControlMode.JOINT_POSITION:
            raise ROSSafetyViolation(
                f"control mode {action.control_mode.value} is not supported by the envelope client",
                check_name="control_mode",
            )
        if action.joint_names != self.joint_names:
            raise ROSSafetyViolation(
                f"action joints {action.joint_names} differ from the robot's {self.joint_names}",
                check_name="joint_names",
            )
        row = action.targets[0]
        for name, value in zip(self.joint_names, row, strict=True):
            if not math.isfinite(value):
                raise ROSSafetyViolation(f"joint '{name}' target is {value}", check_name="non_finite")
        clamp = self.mode is SafetyMode.CLAMP
        checked = list(row)
        reference = self._reference
        for i, value in enumerate(checked):
            lo, hi = self._lower[i], self._upper[i]
            if reference is not None:
                lo = max(lo, reference[i] - self._max_step[i])
                hi = min(hi, reference[i] + self._max_step[i])
                if lo > hi:  # reference outside the limits: move back towards them only
                    lo = hi = min(max(reference[i], self._lower[i]), self._upper[i])
            if value < lo or value > hi:
                if not clamp:
                    limit = "step" if self._lower[i] <= value <= self._upper[i] else "joint_limit"
                    raise ROSSafetyViolation(
                        f"joint '{self.joint_names[i]}' target {value:.4f} outside [{lo:.4f}, {hi:.4f}]",
                        check_name=limit,
                    )
                checked[i] = hi if value > hi else lo
        if checked == row and action.horizon == 1:
            return None
        return Action.model_construct(
            control_mode=action.control_mode,
            joint_names=action.joint_names,
            targets=[checked],
            confidence=action.confidence,
            stamp_ns=action.stamp_ns,
            skill_id=action.skill_id,
        )
