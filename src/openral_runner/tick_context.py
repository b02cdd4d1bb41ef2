"""``TickContext``: everything one tick learns, in one place, turned into its ``TickResult`` once.

The base opens a context when a tick starts (index, start, deadline); the subclass's phases write
their timings, the action requested and sent, why it was withheld, stale sensors and the world
state into it; the deadline check writes the lateness. When the tick ends the base builds the
``TickResult`` from it, once, without re-validating what the runner itself computed.

The result is read off ``TickResult.model_fields``: a context attribute named like a result field
is that field's value; ``start_ns``, ``withheld_reason`` and ``deadline_missed`` are derived here,
``tick_ms`` and ``trace_context`` are measured by the base at the end, and a field the context does
not carry takes its default. Adding a field to ``TickResult`` needs no edit here until a phase has a
value for it (then it becomes an attribute of the context, of the same name and type: the phases
assign it, so it is written out for the type checker, and importing this module refuses a context
attribute whose type differs from its field's).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Final, get_type_hints

from pydantic.fields import FieldInfo

from openral_core import TickResult, WithheldReason, WorldState

_BUILT_HERE: Final = ("start_ns", "withheld_reason", "deadline_missed", "tick_ms", "trace_context")


@dataclass
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
    intervention: bool | None = None
    active_skill: str | None = None
    policy_action: list[float] | None = None
    handover_ramp: bool | None = None
    chunk_id: int | None = None
    """The chunk the action's row came from (the executor's request id); ``None``: an action of its own."""

    def withhold(self, reason: WithheldReason) -> None:
        """Record why the action did not reach the robot (the first reason given stands)."""
        if self.withheld is None:
            self.withheld = reason

    def result(self, *, tick_ms: float, trace_context: str | None) -> TickResult:
        """The tick's ``TickResult`` (every field set here, so it is built without validation).

        A copy of the context's attributes, less those that are the context's own, is the result's
        field dict: one C-level copy instead of a lookup per field, on a path taken every tick.
        """
        values = self.__dict__.copy()
        for name in _CONTEXT_ONLY:
            del values[name]
        values["start_ns"] = int(self.start_s * 1e9)
        values["withheld_reason"] = self.withheld
        values["deadline_missed"] = self.lateness_ms > 0.0
        values["tick_ms"] = tick_ms
        values["trace_context"] = trace_context
        for name, info in _DEFAULTED:
            values[name] = info.get_default(call_default_factory=True)
        return TickResult.trusted(values)


def _split(context: type[TickContext]) -> tuple[tuple[str, ...], tuple[tuple[str, FieldInfo], ...]]:
    """The ``context``'s own attributes (not result fields), and the result fields it does not carry.

    Raises:
        TypeError: A required ``TickResult`` field has no value here (there is no default to take),
            a field built here is also an attribute, or an attribute's type is not its field's.
    """
    carried = [f.name for f in fields(context)]
    hints = get_type_hints(context)
    for name in carried:
        info = TickResult.model_fields.get(name)
        if name in _BUILT_HERE:
            raise TypeError(f"TickResult.{name} is built by TickContext.result(), not carried as an attribute")
        if info is not None and hints[name] != info.annotation:
            raise TypeError(f"{context.__name__}.{name} is {hints[name]}, but TickResult.{name} is {info.annotation}")
    own = tuple(name for name in carried if name not in TickResult.model_fields)
    defaulted = []
    for name, info in TickResult.model_fields.items():
        if name in carried or name in _BUILT_HERE:
            continue
        if info.is_required():
            raise TypeError(f"TickResult.{name} is required, but {context.__name__} has no {name}")
        defaulted.append((name, info))
    return own, tuple(defaulted)


_CONTEXT_ONLY, _DEFAULTED = _split(TickContext)
