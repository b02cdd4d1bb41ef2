"""The two observer bases, importable from the runner: they live in :mod:`openral_observability`."""

from openral_observability.latest_observer import LatestPerKeyObserver
from openral_observability.queued_observer import QueuedObserver

__all__ = ["LatestPerKeyObserver", "QueuedObserver"]
