"""Metric instruments on the OpenTelemetry API, created once per meter provider.

Instruments from the API's proxy meter re-bind when an SDK provider is installed, so
creating them at first use is safe and cheap per tick.
"""

from __future__ import annotations

import math
from functools import cache

from opentelemetry import metrics
from opentelemetry.metrics import Counter, Histogram, UpDownCounter
from opentelemetry.util.types import Attributes

from openral_observability import semconv


@cache
def _meter() -> metrics.Meter:
    return metrics.get_meter(semconv.METER_NAME)


@cache
def histogram(name: str, unit: str = "ms") -> Histogram:
    """A cached histogram instrument."""
    return _meter().create_histogram(name, unit=unit)


@cache
def counter(name: str) -> Counter:
    """A cached monotonic counter instrument."""
    return _meter().create_counter(name)


@cache
def up_down_counter(name: str) -> UpDownCounter:
    """A cached up-down counter instrument."""
    return _meter().create_up_down_counter(name)


def record_histogram_ms(name: str, value_ms: float, attributes: Attributes = None) -> None:
    """Record a duration; negative and non-finite values are dropped, not exported."""
    if value_ms >= 0.0 and math.isfinite(value_ms):
        histogram(name).record(value_ms, attributes)


def add(name: str, amount: int = 1, attributes: Attributes = None) -> None:
    """Add to a counter."""
    counter(name).add(amount, attributes)
