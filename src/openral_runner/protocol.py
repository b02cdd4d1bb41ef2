"""The ``InferenceRunner`` Protocol: what every runner shape (hardware, sim) provides."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from openral_core import RunResult, TickResult


@runtime_checkable
class InferenceRunner(Protocol):
    """A rate-limited loop around one skill.

    ``tick`` runs one tick now, without cadence; ``run`` ticks on an absolute schedule at
    ``rate_hz`` until a limit, a stop request, or the runner's own termination condition.
    """

    rate_hz: float

    def activate(self) -> None:
        """Open sensors, HAL and whatever the loop needs; roll back on failure."""

    def tick(self) -> TickResult:
        """Run one tick and record it."""

    def run(self, max_ticks: int | None = None, *, duration_s: float | None = None) -> RunResult:
        """Tick at ``rate_hz`` and return the aggregate."""

    def deactivate(self) -> None:
        """Release what ``activate`` opened; idempotent."""
