"""``TickObserver``: the seam for everything that watches ticks (visualisers, recorders, dashboards).

Observers are called on the tick thread right after each tick is accounted, so they must
only hand data over (a reference into a queue) and do their work elsewhere. An observer
that raises is logged and detached; it never stops the robot.

A deployment lists observers in its ``observers:`` block; each is a plugin in the
``openral.observers`` entry-point group built with
``Cls.from_config(params, robot=..., env=..., base_dir=...)``, which validates ``params`` with
its own typed model and does no I/O that would need undoing (``openral validate`` builds it).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from openral_core import TickResult, WorldState


@runtime_checkable
class TickObserver(Protocol):
    """Receives every tick and the world state the skill saw (``None`` when none was built)."""

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Take note of one tick; must not block."""

    def close(self) -> None:
        """Flush and release; called once when the runner deactivates."""
