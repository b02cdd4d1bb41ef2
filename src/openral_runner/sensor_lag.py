"""Whether each camera kept up with the loop, measured per read, and what to change when it did not.

A stale read withholds a tick; a bare ``stale_sensor`` does not say whether the camera is broken,
too slow for its rate, or starved by the machine. The runner counts every read of every sensor
here, with the age of each stale frame against the sensor's own limit, and the capture's own
report (requested vs delivered fps, render or read cost) when its reader keeps one. From these,
:func:`lag_line` makes the one line a person reads.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

LAG_STALE_SHARE = 0.01
"""A sensor with more stale reads than this share of its reads is reported as not keeping up."""

_GENERIC_ADVICE = "lower its fps or image size, or give the process more CPU"


@runtime_checkable
class ReportingReader(Protocol):
    """A reader that reports its capture: requested and delivered fps, cost per frame, and its own advice.

    The keys read here are optional: ``requested_fps``, ``delivered_fps``, ``render_ms``, and
    ``advice`` (what to change when the capture cannot keep up, in the backend's own terms).
    """

    sensor_id: str

    def report(self) -> dict[str, Any]:
        """The capture's figures so far, JSON-safe."""


@dataclass
class SensorReads:
    """Reads of one sensor in one run, and the ages of its stale frames."""

    max_age_ms: float | None = None
    reads: int = 0
    stale: int = 0
    unaged: int = 0
    stale_age_ms_sum: float = 0.0
    stale_age_ms_max: float = 0.0

    def clear(self) -> None:
        """Forget every read: a new run counts its own."""
        self.max_age_ms = None
        self.reads = self.stale = self.unaged = 0
        self.stale_age_ms_sum = self.stale_age_ms_max = 0.0

    def stale_read(self, age_ms: float | None, max_age_ms: float | None) -> None:
        """The read found no frame within ``max_age_ms`` (``age_ms`` ``None``: no frame yet, or no set in sync)."""
        self.stale += 1
        if max_age_ms is not None:
            self.max_age_ms = max_age_ms
        if age_ms is None:
            self.unaged += 1
            return
        self.stale_age_ms_sum += age_ms
        self.stale_age_ms_max = max(self.stale_age_ms_max, age_ms)

    def summary(self) -> dict[str, Any]:
        """The figures as plain data for ``RunResult.metadata``."""
        aged = self.stale - self.unaged
        return {
            "reads": self.reads,
            "stale_reads": self.stale,
            "stale_share": round(self.stale / self.reads, 4) if self.reads else 0.0,
            "stale_age_ms_mean": round(self.stale_age_ms_sum / aged, 1) if aged else None,
            "stale_age_ms_max": round(self.stale_age_ms_max, 1) if aged else None,
            "max_age_ms": self.max_age_ms,
        }


def lag_line(sensor_id: str, figures: dict[str, Any]) -> str | None:
    """One line saying that ``sensor_id`` did not keep up, with the measurements and what to change.

    ``figures`` is the sensor's entry of ``RunResult.metadata["sensors"]``: a
    :meth:`SensorReads.summary` merged with the reader's report. ``None`` when the sensor kept up
    (no more than :data:`LAG_STALE_SHARE` of its reads were stale).
    """
    reads = int(figures.get("reads") or 0)
    stale = int(figures.get("stale_reads") or 0)
    if stale == 0 or (reads and stale / reads <= LAG_STALE_SHARE):
        return None
    parts = [f"sensor '{sensor_id}' did not keep up: {stale} of {reads} reads were stale"]
    limit = figures.get("max_age_ms")
    mean, worst = figures.get("stale_age_ms_mean"), figures.get("stale_age_ms_max")
    if worst is not None:
        against = f", against max_age_ms {limit:g}" if limit is not None else ""
        parts.append(f" (their frames {mean:.0f} ms old on average, up to {worst:.0f} ms{against})")
    delivered, requested = figures.get("delivered_fps"), figures.get("requested_fps")
    if delivered is not None and requested is not None:
        cost = figures.get("render_ms")
        per_frame = f", {cost:.0f} ms per render" if cost else ""
        parts.append(f"; it delivered {delivered:.1f} of {requested:g} fps{per_frame}")
    advice = figures.get("advice") or _GENERIC_ADVICE
    raise_limit = "raise max_age_ms" if limit is None else f"raise max_age_ms above {limit:g}"
    parts.append(f". To fix: {advice}; or {raise_limit} if the skill tolerates older frames")
    return "".join(parts)


__all__ = ["LAG_STALE_SHARE", "ReportingReader", "SensorReads", "lag_line"]
