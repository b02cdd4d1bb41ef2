"""The observer seam, importable from the runner: it lives in :mod:`openral_observability.observer`."""

from openral_observability.observer import StartableObserver, Thumbnail, ThumbnailSubscriber, TickObserver

__all__ = ["StartableObserver", "Thumbnail", "ThumbnailSubscriber", "TickObserver"]
