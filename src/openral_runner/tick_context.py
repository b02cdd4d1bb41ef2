"""``TickContext``: everything one tick learns, in one place, turned into its ``TickResult`` once.

The base opens a context when a tick starts (index, start, deadline); the subclass's phases write
their timings, the action requested and sent, why it was withheld, stale sensors and the world
state into it; the deadline check writes the lateness. When the tick ends the base builds the
``TickResult`` from it, once, without re-validating what the runner itself computed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from openral_core import TickResult, WithheldReason, WorldState


@dataclass(slots=True)
class TickContext:
    """The facts of the tick under way. Phases write the fields they own; the base reads them at the end."""

    tick_idx: int
    start_s: float
    deadline_s: float
    sensors_ms: float = 0.0
    world_state_ms: float = 0.0
    inference_ms: float = 0.0
    safety_ms: float = 0.0
    hal_ms: float = 0.0
    action_applied: bool = False
    withheld: WithheldReason | None = None
    safety_violations: list[str] = field(default_factory=list)
    stale_sensors: list[str] = field(default_factory=list)
    requested_action: list[float] | None = None
    sent_action: list[float] | None = None
    lateness_ms: float = 0.0
    deadline_checked: bool = False
    world: WorldState | None = None
    step_idx: int | None = None
    episode_idx: int | None = None
    reward: float | None = None
    terminated: bool | None = None
    truncated: bool | None = None

    def withhold(self, reason: WithheldReason) -> None:
        """Record why the action did not reach the robot (the first reason given stands)."""
        if self.withheld is None:
            self.withheld = reason

    def result(self, *, tick_ms: float, trace_context: str | None) -> TickResult:
        """The tick's ``TickResult`` (every field set here, so it is built without validation)."""
        return TickResult.trusted(
            {
                "tick_idx": self.tick_idx,
                "start_ns": int(self.start_s * 1e9),
                "tick_ms": tick_ms,
                "sensors_ms": self.sensors_ms,
                "world_state_ms": self.world_state_ms,
                "inference_ms": self.inference_ms,
                "safety_ms": self.safety_ms,
                "hal_ms": self.hal_ms,
                "action_applied": self.action_applied,
                "withheld_reason": self.withheld,
                "safety_violations": self.safety_violations,
                "stale_sensors": self.stale_sensors,
                "deadline_missed": self.lateness_ms > 0.0,
                "lateness_ms": self.lateness_ms,
                "requested_action": self.requested_action,
                "sent_action": self.sent_action,
                "trace_context": trace_context,
                "step_idx": self.step_idx,
                "episode_idx": self.episode_idx,
                "reward": self.reward,
                "terminated": self.terminated,
                "truncated": self.truncated,
            }
        )
