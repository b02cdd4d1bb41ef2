"""The attributes of a recorded ``rskill.tick`` span, from the tick's result."""

from __future__ import annotations

from typing import Any, Final

from openral_core import TickResult
from openral_observability import semconv

_OPTIONAL: Final = (
    ("step_idx", semconv.ATTR_STEP_IDX),
    ("episode_idx", semconv.ATTR_EPISODE_IDX),
    ("reward", semconv.ATTR_REWARD),
    ("terminated", semconv.ATTR_TERMINATED),
    ("truncated", semconv.ATTR_TRUNCATED),
)


def tick_span_attributes(result: TickResult, base: dict[str, Any]) -> dict[str, Any]:
    """Per-phase timings and the tick's outcome, on top of ``base`` (the runner's metric labels).

    Returns a new dict each call: the tick span keeps it.
    """
    attributes: dict[str, Any] = {
        **base,
        semconv.ATTR_TICK_IDX: result.tick_idx,
        semconv.ATTR_TICK_MS: result.tick_ms,
        semconv.ATTR_SENSORS_MS: result.sensors_ms,
        semconv.ATTR_WORLD_STATE_MS: result.world_state_ms,
        semconv.ATTR_INFERENCE_MS: result.inference_ms,
        semconv.ATTR_SAFETY_MS: result.safety_ms,
        semconv.ATTR_HAL_MS: result.hal_ms,
        semconv.ATTR_ACTION_APPLIED: result.action_applied,
        semconv.ATTR_SAFETY_VIOLATIONS: len(result.safety_violations),
    }
    if result.withheld_reason is not None:
        attributes[semconv.ATTR_WITHHELD_REASON] = result.withheld_reason
    if result.deadline_missed:
        attributes[semconv.ATTR_LATENESS_MS] = result.lateness_ms
    for name, attr in _OPTIONAL:
        value = getattr(result, name)
        if value is not None:
            attributes[attr] = value
    return attributes
