"""The ``SensorReader`` Protocol: the seam between capture backends and the runner."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from openral_core import SensorFrame


@runtime_checkable
class SensorReader(Protocol):
    """One sensor's capture, running in the background and serving its latest frame.

    Backends live in ``openral_runner.backends`` and register in ``openral.sensor_backends``.

    ``read_latest`` never blocks on the device: it returns the freshest buffered frame, or
    raises ``ROSPerceptionStale`` when there is none yet or it is older than ``max_age_ms``
    (the backend's configured limit when ``None``), and ``ROSRuntimeError`` when the reader
    is closed or its device failed.
    """

    sensor_id: str

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()``."""

    def open(self) -> None:
        """Acquire the device and start background capture. Idempotent."""

    def close(self) -> None:
        """Stop capture and release the device. Idempotent."""

    def read_latest(self, max_age_ms: float | None = None) -> SensorFrame:
        """The most recent frame, without waiting for a new one."""
