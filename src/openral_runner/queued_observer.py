"""The every-tick observer base, importable from the runner: it lives in :mod:`openral_observability`."""

from openral_observability.latest_observer import LatestPerKeyObserver
from openral_observability.queued_observer import QueuedObserver

__all__ = ["LatestPerKeyObserver", "QueuedObserver"]
