"""The ``perception`` observer at its specification path; it lives in :mod:`openral_perception.observer`."""

from openral_perception.observer import PerceptionObserver, build_detectors, build_publisher

__all__ = ["PerceptionObserver", "build_detectors", "build_publisher"]
