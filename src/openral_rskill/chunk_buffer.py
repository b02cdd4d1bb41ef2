"""``ChunkBuffer``: a chunking policy's targets indexed by tick. Pure numpy: no threads, no clock, no telemetry.

Row ``i`` of the buffer is the absolute target for tick ``base_tick + i``. The buffer knows ticks
only as the integers it is told, so every rule below is checkable without a worker:

* **Placing a chunk** observed at tick ``k`` on tick ``t``: row ``j`` is for tick ``k + j``, so
  its first ``t - k`` rows are for ticks already past and are skipped (not under ``stale_start``,
  where a chunk runs from its first row as it arrives). At most ``executed_rows`` rows of a chunk
  count. A chunk left with fewer than ``min_rows`` rows is refused and the buffer is unchanged.
* **Seams**: the placed rows ``replace`` what was left from tick ``t`` on, ``crossfade`` into it
  over ``crossfade_rows`` rows, or are ``ensemble``d with every earlier prediction for the same
  tick (ACT's weights ``exp(-m * i)`` for the ``i``-th oldest, kept as running sums: no per-row
  Python objects). In every mode the buffer then ends where the new chunk ends.
* **Reading** the row for a tick drops the rows of earlier ticks; a tick past the last row empties
  the buffer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from openral_core import ExecutorConfig, SeamMode


@dataclass(frozen=True)
class Placement:
    """What became of a placed chunk.

    Attributes:
        skipped: Rows dropped for ticks already past (0 under ``stale_start``).
        used: Rows now in the buffer; 0 when the chunk was refused (fewer than ``min_rows`` left).
    """

    skipped: int
    used: int

    @property
    def refused(self) -> bool:
        """Whether the chunk was refused (too few rows left for the ticks to come)."""
        return self.used == 0


class ChunkBuffer:
    """Absolute targets by tick, with the executor's seam, skipping and min-rows rules.

    Args:
        dims: Values per row (the action's dimensions).
        config: The executor's settings: ``seam``, ``crossfade_rows``, ``ensemble_decay``,
            ``min_rows``, ``executed_rows`` and ``indexing`` are read here.
    """

    def __init__(self, dims: int, config: ExecutorConfig) -> None:
        self.dims = dims
        self.config = config
        self.seam = config.seam
        self.stale_start = config.indexing == "stale_start"
        self.base_tick = 0
        """The tick of row 0."""
        self._targets = np.zeros((0, dims))
        self._ensembling = config.seam is SeamMode.ENSEMBLE
        # ENSEMBLE: per buffered row, the weighted sum of every prediction for its tick, the sum of
        # their weights and how many there were (the next one's weight is exp(-m * count)).
        self._sums = np.zeros((0, dims))
        self._weights = np.zeros(0)
        self._counts = np.zeros(0)

    def __len__(self) -> int:
        """Rows buffered from :attr:`base_tick` on."""
        return len(self._targets)

    def ahead(self, tick: int) -> int:
        """Rows buffered for ``tick`` and after it."""
        return max(0, self.base_tick + len(self._targets) - tick)

    def rows_from(self, tick: int) -> np.ndarray:
        """The rows for ``tick`` and after, a view (all of them when ``tick`` is before :attr:`base_tick`)."""
        start = tick - self.base_tick
        return self._targets if start <= 0 else self._targets[start:]

    def row_for(self, tick: int) -> np.ndarray | None:
        """The target for ``tick`` (a view), dropping the rows of earlier ticks; ``None`` when there is none.

        A tick past the last row empties the buffer; a tick before :attr:`base_tick` has no row.
        """
        index = tick - self.base_tick
        size = len(self._targets)
        if 0 <= index < size:
            if index > 0:
                self._drop(index)
                self.base_tick = tick
            row: np.ndarray = self._targets[0]
            return row
        if index >= size and size:
            self.clear()
        return None

    def clear(self) -> None:
        """Drop every row (a new episode, or a source that went down)."""
        self._targets = self._targets[:0]
        if self._ensembling:
            self._sums = self._sums[:0]
            self._weights = self._weights[:0]
            self._counts = self._counts[:0]

    def place(self, targets: np.ndarray, *, obs_tick: int, tick: int) -> Placement:
        """Place a chunk of absolute ``targets`` (``(rows, dims)``) observed at ``obs_tick`` on ``tick``.

        Row ``j`` is for tick ``obs_tick + j``; see the module's rules for skipping, refusing and seams.
        """
        executed = self.config.executed_rows
        if executed is not None:
            targets = targets[:executed]
        skipped = 0 if self.stale_start else min(max(0, tick - obs_tick), len(targets))
        usable = targets[skipped:]
        if len(usable) < self.config.min_rows:
            return Placement(skipped=skipped, used=0)
        self._merge(usable, tick)
        return Placement(skipped=skipped, used=len(usable))

    # -- internals -----------------------------------------------------------------------------

    def _drop(self, count: int) -> None:
        self._targets = self._targets[count:]
        if self._ensembling:
            self._sums = self._sums[count:]
            self._weights = self._weights[count:]
            self._counts = self._counts[count:]

    def _merge(self, usable: np.ndarray, tick: int) -> None:
        start = max(0, tick - self.base_tick)
        old = self._targets[start:]
        if self._ensembling:
            merged = self._ensembled(usable, start)
        elif self.seam is SeamMode.CROSSFADE and len(old):
            merged = np.array(usable, dtype=np.float64, copy=True)
            blend = min(self.config.crossfade_rows, len(old), len(usable))
            alpha = (np.arange(1, blend + 1) / (blend + 1))[:, None]
            merged[:blend] = (1 - alpha) * old[:blend] + alpha * usable[:blend]
        else:
            merged = usable
        self.base_tick = tick
        self._targets = merged

    def _ensembled(self, usable: np.ndarray, start: int) -> np.ndarray:
        """Add ``usable`` as the newest prediction of the ticks from ``start`` on; the weighted means."""
        rows = len(usable)
        known = max(0, min(rows, len(self._counts) - start))
        sums = np.zeros((rows, self.dims))
        weights = np.zeros(rows)
        counts = np.zeros(rows)
        sums[:known] = self._sums[start : start + known]
        weights[:known] = self._weights[start : start + known]
        counts[:known] = self._counts[start : start + known]
        weight = np.exp(-self.config.ensemble_decay * counts)
        sums += weight[:, None] * usable
        weights += weight
        self._sums, self._weights, self._counts = sums, weights, counts + 1
        return sums / weights[:, None]


__all__ = ["ChunkBuffer", "Placement"]
