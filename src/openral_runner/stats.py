"""Bounded per-tick sample storage for honest run statistics at any rate and duration."""

from __future__ import annotations

import numpy as np

DEFAULT_CAPACITY = 262_144
"""Samples kept for percentiles (~2.4 h at 30 Hz, ~4 min at 1 kHz); mean and max cover every sample."""


class RollingSamples:
    """Preallocated ring of float samples with exact count, mean and max over all samples.

    Percentiles are computed over the most recent ``capacity`` samples. Appending is O(1)
    and allocates nothing, so it is safe on the tick path.
    """

    __slots__ = ("_buffer", "_capacity", "_count", "_max", "_sum")

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        self._capacity = capacity
        self._buffer = np.empty(capacity, dtype=np.float64)
        self.clear()

    def clear(self) -> None:
        """Forget every sample."""
        self._count = 0
        self._sum = 0.0
        self._max = 0.0

    def add(self, value: float) -> None:
        """Record one sample."""
        self._buffer[self._count % self._capacity] = value
        self._count += 1
        self._sum += value
        if value > self._max or self._count == 1:
            self._max = value

    def __len__(self) -> int:
        return self._count

    @property
    def mean(self) -> float:
        """Mean over every sample (0 when empty)."""
        return self._sum / self._count if self._count else 0.0

    @property
    def max(self) -> float:
        """Largest sample (0 when empty)."""
        return self._max

    def window(self) -> np.ndarray:
        """The retained samples (a copy, oldest order not guaranteed)."""
        return self._buffer[: min(self._count, self._capacity)].copy()

    def percentile(self, q: float) -> float:
        """Linear-interpolation percentile ``q`` in [0, 100] over retained samples (0 when empty)."""
        if self._count == 0:
            return 0.0
        return float(np.percentile(self._buffer[: min(self._count, self._capacity)], q))
