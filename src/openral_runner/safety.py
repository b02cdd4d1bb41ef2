"""The ``SafetyClient`` seam: every action passes one before it reaches the HAL."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import structlog
from opentelemetry import trace

from openral_core import Action, JointState, RobotManifest, SafetyConfig, SafetyEnvelope
from openral_observability import semconv

_log = structlog.get_logger(__name__)


@runtime_checkable
class SafetyClient(Protocol):
    """Checks an action against the robot's envelope.

    ``check_action`` returns ``None`` to allow the action unchanged, returns a replacement
    action (clamped into the envelope) to send instead, or raises ``ROSSafetyViolation`` to
    reject it. The runner times the call inside a ``safety.check`` span. Raising
    ``ROSEStopRequested`` stops the loop and e-stops the robot. The runner is the
    supervisor boundary that catches both; nothing else does.

    This is the whole contract a client must meet. A client that measures steps from the
    robot's state also implements :class:`SafetyStateObserver` and :class:`SafetyCommitListener`;
    the runner finds out which when the client is given to it, not per tick.
    """

    envelope: SafetyEnvelope

    def check_action(self, action: Action) -> Action | None:
        """Allow, replace or reject ``action``."""
        ...


class SafetyClientPlugin(Protocol):
    """What the ``openral.safety_clients`` group holds: a class built from the deployment's ``safety`` block."""

    def from_config(self, config: SafetyConfig, *, robot: RobotManifest, rate_hz: float) -> SafetyClient:
        """Build the client guarding ``robot`` at ``rate_hz`` ticks per second (a step limit is per tick).

        Raises:
            ROSConfigError: The block asks for what the robot's manifest cannot give.
        """
        ...


@runtime_checkable
class SafetyStateObserver(Protocol):
    """A safety client that wants the joints measured each tick, before the skill steps."""

    def observe_state(self, state: JointState) -> None:
        """The joints measured this tick (a step limit is measured from them)."""
        ...


@runtime_checkable
class SafetyCommitListener(Protocol):
    """A safety client that wants to know which action actually reached the robot each tick."""

    def commit(self, action: Action) -> None:
        """The action the HAL accepted this tick (a check may replace or the deadline withhold the requested one)."""
        ...


class NullSafetyClient(SafetyClient):
    """Allows every action. Only for deployments that ask for it (``safety.client: null``).

    Each call still annotates the ``safety.check`` span so traces show the seam is wired.
    """

    def __init__(self, envelope: SafetyEnvelope | None = None) -> None:
        self.envelope = envelope or SafetyEnvelope()

    @classmethod
    def from_config(cls, config: SafetyConfig, *, robot: RobotManifest, rate_hz: float) -> NullSafetyClient:
        """Plugin constructor; warns because nothing will be checked."""
        _log.warning(
            "safety checking is disabled (safety.client: null): actions reach the robot unchecked",
            robot_id=robot.robot_id,
        )
        return cls()

    def check_action(self, action: Action) -> Action | None:
        """Allow ``action`` unchanged, annotating the runner's ``safety.check`` span."""
        span = trace.get_current_span()
        if span.is_recording():
            span.set_attributes(
                {
                    semconv.ATTR_SAFETY_SEVERITY: "info",
                    semconv.ATTR_SAFETY_CONTROL_MODE: action.control_mode.value,
                    semconv.ATTR_SAFETY_HORIZON: action.horizon,
                    semconv.ATTR_SAFETY_MAX_EE_SPEED: self.envelope.max_ee_speed_m_s,
                    semconv.ATTR_SAFETY_MAX_FORCE: self.envelope.max_force_n,
                }
            )
        return None
