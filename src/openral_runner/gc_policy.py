"""Garbage collection between ticks: no collector pause inside a tick.

Python's cyclic collector runs whenever allocations cross a threshold, in whichever thread
allocated, and stops every thread while it runs: a young-generation pass costs 0.1–1 ms, a
full one tens of milliseconds once a process holds a few hundred thousand objects. A tick
that happens to allocate the triggering object, or that wakes while a background thread
collects, pays for it.

:class:`BetweenTicksCollector` takes that choice away from the allocator for the length of a
run. At the start it collects once and freezes every surviving object (the model, the config,
imported modules) out of later collections. It then turns automatic collection off, and after
each tick that leaves enough idle time before the next slot, it collects the generations
Python would have collected by now. Its counts follow Python's own thresholds. Garbage still
gets collected, cycles included; only the moment changes. At the end of the run it unfreezes
and restores the collector as it found it.
"""

from __future__ import annotations

import gc
import time
from typing import Any, Final

MIN_IDLE_S: Final = 0.5e-3
"""Idle time before the next slot needed to collect: a young-generation pass fits with room to spare."""
BACKLOG_FACTOR: Final = 8
"""A loop that never leaves :data:`MIN_IDLE_S` still collects once this many thresholds' worth is pending."""


class BetweenTicksCollector:
    """Pauses automatic garbage collection for a run and collects in the idle time after ticks.

    Use :meth:`start` / :meth:`stop` around the run (both idempotent) and call
    :meth:`collect_if_due` after each tick.
    """

    def __init__(self) -> None:
        self._active = False
        self._was_enabled = False
        self._thresholds = gc.get_threshold()
        self.collections = [0, 0, 0]
        self.max_pause_ms = 0.0
        self.frozen = 0

    def start(self) -> None:
        """Collect once, freeze what survives, and turn automatic collection off."""
        if self._active:
            return
        self._was_enabled = gc.isenabled()
        self._thresholds = gc.get_threshold()
        gc.collect()
        gc.freeze()
        self.frozen = gc.get_freeze_count()
        gc.disable()
        self._active = True

    def stop(self) -> None:
        """Unfreeze and restore automatic collection if it was on."""
        if not self._active:
            return
        self._active = False
        gc.unfreeze()
        if self._was_enabled:
            gc.enable()

    def collect_if_due(self, idle_s: float) -> int | None:
        """Collect the generations whose thresholds are crossed, if ``idle_s`` allows it.

        Args:
            idle_s: Time left until the next tick's slot.

        Returns:
            The generation collected (0, 1 or 2), or ``None``.
        """
        if not self._active:
            return None
        young, middle, old = gc.get_count()
        t0, t1, t2 = self._thresholds
        if t0 <= 0 or young < t0:
            return None
        if idle_s < MIN_IDLE_S and young < BACKLOG_FACTOR * t0:
            return None
        generation = 2 if middle >= t1 and old >= t2 else 1 if middle >= t1 else 0
        started = time.perf_counter()
        gc.collect(generation)
        pause_ms = (time.perf_counter() - started) * 1e3
        self.collections[generation] += 1
        self.max_pause_ms = max(self.max_pause_ms, pause_ms)
        return generation

    @property
    def report(self) -> dict[str, Any]:
        """Collections per generation, the longest pause and how many objects were frozen."""
        return {
            "policy": "between_ticks",
            "collections": list(self.collections),
            "max_pause_ms": round(self.max_pause_ms, 3),
            "frozen_objects": self.frozen,
        }
