"""The attributes of a recorded ``rskill.tick`` span, rendered from the tick's result.

Which fields reach the span, and under which names, is each field's ``SpanAttribute`` (read into
:data:`openral_observability.semconv.TICK_ATTRIBUTES`); how each is rendered follows from its
``TickResult`` type, worked out once at import:

- a list becomes its length (``skill.safety_violations`` counts the violations);
- an optional field (default ``None``) is set only when the tick has a value, so a zero reward is
  kept and an absent one is not;
- ``lateness_ms`` is set only when the deadline was missed;
- every other field is always set.
"""

from __future__ import annotations

from typing import Any, Final, get_origin

from openral_core import TickResult
from openral_observability import semconv

_LATE_ONLY: Final = "lateness_ms"

_Pairs = tuple[tuple[str, str], ...]


def _rendering() -> tuple[_Pairs, _Pairs, _Pairs]:
    """The ``(field, attribute)`` pairs of :data:`semconv.TICK_ATTRIBUTES` by rendering: always, counted, when set."""
    always: list[tuple[str, str]] = []
    counted: list[tuple[str, str]] = []
    when_set: list[tuple[str, str]] = []
    for name, attribute in semconv.TICK_ATTRIBUTES.items():
        if name == _LATE_ONLY:
            continue
        field = TickResult.model_fields[name]
        if get_origin(field.annotation) is list:
            counted.append((name, attribute))
        elif field.default is None:
            when_set.append((name, attribute))
        else:
            always.append((name, attribute))
    return tuple(always), tuple(counted), tuple(when_set)


_ALWAYS, _COUNTED, _WHEN_SET = _rendering()
_LATENESS: Final = semconv.TICK_ATTRIBUTES[_LATE_ONLY]


def tick_span_attributes(result: TickResult, base: dict[str, Any]) -> dict[str, Any]:
    """Per-phase timings and the tick's outcome, on top of ``base`` (the runner's metric labels).

    Returns a new dict each call: the tick span keeps it. Reads the field values from the
    result's ``__dict__`` (a dictionary lookup, cheaper than a model attribute on the tick thread).
    """
    values = result.__dict__
    attributes = {**base}
    for name, attribute in _ALWAYS:
        attributes[attribute] = values[name]
    for name, attribute in _COUNTED:
        attributes[attribute] = len(values[name])
    for name, attribute in _WHEN_SET:
        value = values[name]
        if value is not None:
            attributes[attribute] = value
    if values["deadline_missed"]:
        attributes[_LATENESS] = values[_LATE_ONLY]
    return attributes
