"""``EnvelopeSafetyClient``: joint limits, step limits, finiteness and an optional workspace box.

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
    ROSConfigError,
    ROSSafetyViolation,
    SafetyConfig,
    SafetyEnvelope,
    SafetyMode,
)
from openral_hal.kinematics import SiteChain, load_site_chain
from openral_runner.safety import SafetyClient, SafetyCommitListener, SafetyStateObserver

# Pull-back into the workspace box: stop within 0.1 mm of the boundary, or when the bracket on
# the step is below 1/4096 of it, or after this many forward-kinematics evaluations.
_BOUNDARY_TOLERANCE_M = 1e-4
_MIN_BRACKET = 1.0 / 4096
_MAX_ITERATIONS = 16


class EnvelopeSafetyClient(SafetyClient, SafetyStateObserver, SafetyCommitListener):
    """Keeps joint-position commands inside the robot's limits, speed envelope and workspace box.

    * Control modes other than joint position, wrong joint sets and non-finite values are
      always rejected.
    * Out-of-range positions (the gripper included: it is a joint with manifest limits like
      any other) are clipped (``clamp``) or rejected (``reject``).
    * The step from the reference (the last command sent, or the measured position before
      the first one) is limited to ``velocity_limit × max_joint_speed_factor / rate_hz``.
      With no reference yet (no state observed) only the position limits apply. A reference
      more than one step outside the position limits is rejected in both modes: no single
      command can be inside both the limits and the step.
    * With a workspace box, the end-effector site of the checked row (forward kinematics of
      the manifest's MuJoCo model, base frame) must lie inside it. ``reject`` rejects a row
      outside; ``clamp`` moves the row back along the straight joint-space segment towards
      the reference (false position on the box violation) to a point tested inside the box,
      within 0.1 mm of its boundary (the reference itself, i.e. hold, when none closer is
      found). A command whose end effector is outside the box is never returned; if the
      reference itself is outside the box, or there is no reference, the action is rejected.

    Args:
        robot: Joint limits and velocity limits (and the MuJoCo model, for the workspace box).
        rate_hz: Tick rate, to turn velocity limits into a per-tick step.
        mode: ``clamp`` or ``reject``.
        envelope: Further limits; ``max_joint_speed_factor`` scales the step limit and
            ``workspace_min`` / ``workspace_max`` enable the workspace box.
        kinematics: End-effector kinematics for the box; by default extracted once from the
            manifest's ``mujoco`` model when the envelope has a box.

    Raises:
        ROSConfigError: The envelope has a workspace box but the robot's manifest names no
            MuJoCo model with an ``ee_site`` (field ``safety.workspace_min``), or the model
            cannot be read; or ``max_joint_speed_factor`` is so small that a joint's step
            underflows to zero.
    """

    def __init__(
        self,
        robot: RobotManifest,
        *,
        rate_hz: float,
        mode: SafetyMode = SafetyMode.CLAMP,
        envelope: SafetyEnvelope | None = None,
        kinematics: SiteChain | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise ROSConfigError(f"rate_hz must be positive, got {rate_hz}", field="rate_hz")
        self.envelope = envelope or SafetyEnvelope()
        self.mode = mode
        self.robot_id = robot.robot_id
        self.joint_names = robot.joint_names
        self._n = len(self.joint_names)
        self._lower = tuple(j.lower for j in robot.joints)
        self._upper = tuple(j.upper for j in robot.joints)
        factor = self.envelope.max_joint_speed_factor
        self._max_step = tuple(j.velocity_limit * factor / rate_hz for j in robot.joints)
        if not all(step > 0 for step in self._max_step):
            raise ROSConfigError(
                f"{factor:g} of the joints' velocity limits at {rate_hz:g} Hz is a step of 0 rad per tick: "
                "no joint could move",
                field="safety.max_joint_speed_factor",
                hint="raise it: 1.0 is the robot's full speed, 0.1 to 0.5 a careful start",
            )
        self._clamp = mode is SafetyMode.CLAMP
        self._reference: list[float] | None = None
        # Box violation of the row last returned by check_action, and of the reference when that
        # row was committed: spares a forward-kinematics evaluation when pulling back.
        self._checked: tuple[list[float], float] | None = None
        self._reference_violation: float | None = None
        self.kinematics: SiteChain | None = None
        self._box: tuple[float, float, float, float, float, float] | None = None
        box_min, box_max = self.envelope.workspace_min, self.envelope.workspace_max
        if box_min is not None and box_max is not None:
            self.kinematics = kinematics or _robot_kinematics(robot)
            self._box = (*box_min, *box_max)

    @classmethod
    def from_config(cls, config: SafetyConfig, *, robot: RobotManifest, rate_hz: float) -> EnvelopeSafetyClient:
        """Plugin constructor from the deployment's ``safety`` block."""
        envelope = SafetyEnvelope(
            max_joint_speed_factor=config.max_joint_speed_factor,
            workspace_min=config.workspace_min,
            workspace_max=config.workspace_max,
        )
        return cls(robot, rate_hz=rate_hz, mode=config.mode, envelope=envelope)

    @property
    def max_step(self) -> tuple[float, ...]:
        """Largest allowed change per tick of each joint, in joint order."""
        return self._max_step

    def in_workspace(self, row: list[float]) -> bool:
        """Whether the end effector of ``row`` lies inside the workspace box (always, without one)."""
        if self.kinematics is None or self._box is None:
            return True
        x, y, z = self.kinematics.position(row)
        x0, y0, z0, x1, y1, z1 = self._box
        return x0 <= x <= x1 and y0 <= y <= y1 and z0 <= z <= z1

    def observe_state(self, state: JointState) -> None:
        """Use the measured position as the step reference until a command has been sent.

        A state with other joints or a non-finite position is ignored.
        """
        if self._reference is None and state.names == self.joint_names:
            positions = list(state.positions)
            if all(math.isfinite(p) for p in positions):
                self._reference = positions

    def commit(self, action: Action) -> None:
        """Record the command the HAL accepted: the reference for the next step limit."""
        first = action.targets[0]
        checked = self._checked
        self._reference_violation = checked[1] if checked is not None and checked[0] is first else None
        self._reference = list(first)

    def check_action(self, action: Action) -> Action | None:
        """Return the checked single-row action to send, ``None`` when ``action`` is that already.

        Raises:
            ROSSafetyViolation: The action is rejected (``check_name``: ``control_mode``,
                ``joint_names``, ``non_finite``, ``joint_limit``, ``step`` or ``workspace``).
        """
        if action.control_mode is not ControlMode.JOINT_POSITION:
            raise ROSSafetyViolation(
                f"control mode {action.control_mode.value} is not supported by the envelope client",
                check_name="control_mode",
            )
        names = self.joint_names
        row = action.targets[0]
        if action.joint_names != names or len(row) != self._n:
            raise ROSSafetyViolation(
                f"action joints {action.joint_names} ({len(row)} values) differ from the robot's {names}",
                check_name="joint_names",
            )
        isfinite = math.isfinite
        for i, value in enumerate(row):
            if not isfinite(value):
                raise ROSSafetyViolation(f"joint '{names[i]}' target is {value}", check_name="non_finite")
        checked = list(row)
        reference = self._reference
        lower, upper, max_step = self._lower, self._upper, self._max_step
        for i in range(self._n):
            value = checked[i]
            lo, hi = lower[i], upper[i]
            if reference is not None:
                ref, step = reference[i], max_step[i]
                # ``if`` is measurably cheaper than max()/min() calls on this hot path.
                if ref - step > lo:  # noqa: PLR1730
                    lo = ref - step
                if ref + step < hi:  # noqa: PLR1730
                    hi = ref + step
                if lo > hi:
                    raise ROSSafetyViolation(
                        f"joint '{names[i]}' is at {ref:.4f}, more than one step ({step:.4f}) outside its limits "
                        f"[{lower[i]:.4f}, {upper[i]:.4f}]; no command can respect both (check the calibration, "
                        "or move the arm back by hand)",
                        check_name="joint_limit",
                    )
            if value < lo or value > hi:
                if not self._clamp:
                    limit = "step" if lower[i] <= value <= upper[i] else "joint_limit"
                    raise ROSSafetyViolation(
                        f"joint '{names[i]}' target {value:.4f} outside [{lo:.4f}, {hi:.4f}]",
                        check_name=limit,
                    )
                checked[i] = hi if value > hi else lo
        if self._box is not None:
            outside = self._violation(checked)
            if outside > 0.0:
                checked, outside = self._pull_back_into_box(checked, outside, reference)
            if checked == row and action.horizon == 1:
                self._checked = (row, outside)
                return None
            self._checked = (checked, outside)
        elif checked == row and action.horizon == 1:
            return None
        return Action.model_construct(
            control_mode=action.control_mode,
            joint_names=action.joint_names,
            targets=[checked],
            confidence=action.confidence,
            stamp_ns=action.stamp_ns,
            skill_id=action.skill_id,
        )

    def _pull_back_into_box(
        self, target: list[float], outside: float, reference: list[float] | None
    ) -> tuple[list[float], float]:
        """A point on [reference, target] whose end effector is inside the box, near its boundary."""
        if not self._clamp:
            raise ROSSafetyViolation(f"end effector {self._outside_message(target)}", check_name="workspace")
        if reference is None:
            raise ROSSafetyViolation(
                f"end effector {self._outside_message(target)}, and there is no reference position to pull "
                "the command back towards",
                check_name="workspace",
            )
        inside = self._reference_violation  # known when the reference is a row this client returned
        if inside is None:
            inside_limits = all(lo <= r <= hi for lo, r, hi in zip(self._lower, reference, self._upper, strict=True))
            inside = self._violation(reference) if inside_limits else math.inf
        if inside > 0.0:
            raise ROSSafetyViolation(
                f"end effector {self._outside_message(target)}, and the reference position is outside the "
                "envelope too (move the arm back into the workspace by hand)",
                check_name="workspace",
            )
        return self._false_position(list(reference), inside, target, outside)

    def _false_position(
        self, anchor: list[float], g_in: float, target: list[float], g_out: float
    ) -> tuple[list[float], float]:
        """Illinois false position on ``t`` in ``anchor + t·(target − anchor)`` for the box boundary.

        Only points tested inside are kept (returned with their violation, ``<= 0``); the result
        is within ``_BOUNDARY_TOLERANCE_M`` of the boundary, or the bracket has shrunk below
        ``_MIN_BRACKET``, or it is ``anchor`` itself.
        """
        delta = [b - a for a, b in zip(anchor, target, strict=True)]
        # Each joint stays between its reference and its checked target, both inside its bounds.
        low = [min(a, b) for a, b in zip(anchor, target, strict=True)]
        high = [max(a, b) for a, b in zip(anchor, target, strict=True)]
        best, best_g = anchor, g_in
        t_in, t_out = 0.0, 1.0
        side = 0
        for _ in range(_MAX_ITERATIONS):
            t = (t_in * g_out - t_out * g_in) / (g_out - g_in)
            candidate = [min(max(a + t * d, lo), hi) for a, d, lo, hi in zip(anchor, delta, low, high, strict=True)]
            g = self._violation(candidate)
            if g <= 0.0:
                best, best_g, t_in, g_in = candidate, g, t, g
                if g > -_BOUNDARY_TOLERANCE_M:
                    break
                if side < 0:
                    g_out *= 0.5
                side = -1
            else:
                t_out, g_out = t, g
                if side > 0:
                    g_in *= 0.5
                side = 1
            if t_out - t_in < _MIN_BRACKET:
                break
        return best, best_g

    def _violation(self, row: list[float]) -> float:
        """How far (metres) the end effector of ``row`` is outside the box; ``<= 0`` inside."""
        assert self.kinematics is not None
        assert self._box is not None
        x, y, z = self.kinematics.position(row)
        x0, y0, z0, x1, y1, z1 = self._box
        return max(x0 - x, x - x1, y0 - y, y - y1, z0 - z, z - z1)

    def _outside_message(self, row: list[float]) -> str:
        assert self.kinematics is not None
        assert self._box is not None
        x, y, z = self.kinematics.position(row)
        lo, hi = self._box[:3], self._box[3:]
        return (
            f"({x:.4f}, {y:.4f}, {z:.4f}) m is outside the workspace box "
            f"[{lo[0]}, {hi[0]}] x [{lo[1]}, {hi[1]}] x [{lo[2]}, {hi[2]}] of robot '{self.robot_id}'"
        )


def _robot_kinematics(robot: RobotManifest) -> SiteChain:
    if robot.mujoco is None or robot.mujoco.ee_site is None:
        raise ROSConfigError(
            f"a workspace box needs the end-effector position, but robot '{robot.robot_id}' has no MuJoCo "
            "model with an ee_site in its manifest to compute it from",
            field="safety.workspace_min",
            hint="remove safety.workspace_min/workspace_max, or add a mujoco model with ee_site to the manifest",
        )
    return load_site_chain(robot)
