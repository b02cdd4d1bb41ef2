"""The ``SensorReader`` Protocol and multi-camera synchronisation over it."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

from openral_core import RobotManifest, ROSPerceptionStale, ROSSyncError, SensorFrame, SensorReaderConfig
from openral_core.config import ModelT, validate_model
from openral_core.config_files import require_user_file
from openral_hal.protocol import HAL


@runtime_checkable
class SensorReader(Protocol):
    """One sensor's capture, running in the background and serving its latest frame.

    This is the whole contract a backend must meet to run under the runner. Backends live in
    ``openral_runner.backends`` or in other packages and register their class in
    ``openral.sensor_backends`` (see :class:`SensorBackendPlugin`).

    ``read_latest`` never blocks on the device: it returns the freshest buffered frame, or
    raises ``ROSPerceptionStale`` when there is none yet or it is older than ``max_age_ms``
    (the backend's configured limit when ``None``), and ``ROSRuntimeError`` when the reader
    is closed or its device failed. Frame ages are measured from the capture stamp.
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


@runtime_checkable
class SyncedSensorReader(SensorReader, Protocol):
    """A reader that can also wait for its next frame (every built-in backend).

    The runner uses it to start its schedule just after a frame and to make multi-camera sets;
    a reader without it is given :class:`PollingSync` when the runner is built.
    """

    def read_synced(self, deadline_ns: int, *, newer_than_ns: int = 0) -> SensorFrame:
        """Wait until a frame captured after ``newer_than_ns`` is available, at most until ``deadline_ns``.

        Both are on the monotonic clock of the capture stamps.

        Raises:
            ROSPerceptionStale: No such frame by the deadline.
            ROSRuntimeError: The reader is closed or failed.
        """


class SensorBackendPlugin(Protocol):
    """What the ``openral.sensor_backends`` group holds: a reader class built from one sensor of the deployment."""

    def from_config(
        self, config: SensorReaderConfig, *, hal: HAL, robot: RobotManifest, base_dir: Path | None = None
    ) -> SensorReader:
        """Build a closed reader; ``backend_params`` are validated with the backend's own model.

        Args:
            config: The sensor's block of the deployment.
            hal: The deployment's HAL (a camera rendered from a simulated robot needs it).
            robot: The robot's manifest.
            base_dir: Folder a relative file path is resolved against (the deployment file's).

        Raises:
            ROSConfigError: A wrong or missing parameter, named as ``sensors[<id>].backend_params.<key>``.
        """
        ...


POLL_INTERVAL_S = 0.0005
"""How often :class:`PollingSync` looks for a newer frame."""


class PollingSync:
    """``read_synced`` for a reader that only has ``read_latest``: polls for a newer frame.

    Everything else is the wrapped reader's. Used only for the waits of start-up and of a
    ``sync:`` set, never for a tick's ordinary read.
    """

    def __init__(self, reader: SensorReader, *, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self.reader = reader
        self.sensor_id = reader.sensor_id
        self._clock_ns = clock_ns

    @property
    def is_open(self) -> bool:
        """The wrapped reader's state."""
        return self.reader.is_open

    def open(self) -> None:
        """Open the wrapped reader."""
        self.reader.open()

    def close(self) -> None:
        """Close the wrapped reader."""
        self.reader.close()

    def read_latest(self, max_age_ms: float | None = None) -> SensorFrame:
        """The wrapped reader's latest frame."""
        return self.reader.read_latest(max_age_ms)

    def read_synced(self, deadline_ns: int, *, newer_than_ns: int = 0) -> SensorFrame:
        """Poll ``read_latest`` until a frame newer than ``newer_than_ns`` arrives or the deadline passes.

        Raises:
            ROSPerceptionStale: No such frame by the deadline.
        """
        age_ms: float | None = None
        # Bounded on the wall clock too, so a clock that does not advance by itself cannot hang it.
        give_up = time.monotonic() + max(0.0, (deadline_ns - self._clock_ns()) / 1e9)
        while True:
            try:
                frame = self.reader.read_latest(float("inf"))
            except ROSPerceptionStale:
                frame = None
            if frame is not None:
                if frame.stamp_ns > newer_than_ns:
                    return frame
                age_ms = (self._clock_ns() - frame.stamp_ns) / 1e6
            if self._clock_ns() >= deadline_ns or time.monotonic() >= give_up:
                raise ROSPerceptionStale(self.sensor_id, age_ms=age_ms, max_age_ms=None)
            time.sleep(POLL_INTERVAL_S)


def with_read_synced(reader: SensorReader, *, clock_ns: Callable[[], int] = time.monotonic_ns) -> SyncedSensorReader:
    """``reader`` itself when it can wait for a frame, else a :class:`PollingSync` around it."""
    if isinstance(reader, SyncedSensorReader):
        return reader
    return PollingSync(reader, clock_ns=clock_ns)


def backend_params_field(config: SensorReaderConfig) -> str:
    """Where a sensor's ``backend_params`` sit in the deployment, as config errors name it."""
    return f"sensors[{config.sensor_id}].backend_params"


def validate_backend_params(model: type[ModelT], config: SensorReaderConfig, *, backend: str) -> ModelT:
    """``config.backend_params`` validated as ``model``; an error names ``sensors[<id>].backend_params.<key>``."""
    return validate_model(
        model,
        dict(config.backend_params),
        source=f"the {backend} sensor backend",
        field_prefix=backend_params_field(config),
    )


def is_file_path(source: str) -> bool:
    """A capture source that names a file (not a URL, a device node or a camera index)."""
    return "://" not in source and not source.startswith("/dev/") and not source.isdigit()


def require_video_file(device: str, base_dir: Path | None, *, sensor_id: str) -> Path:
    """The video file a sensor names, resolved against the deployment's folder; it must exist now.

    Checked when the deployment is built, so ``openral validate`` refuses a missing file instead of
    ``deploy`` failing at start-up.

    Raises:
        ROSConfigError: The file does not exist or is not a regular file.
    """
    return require_user_file(device, base_dir, field=f"sensors[{sensor_id}].backend_params.device", what="video file")


def read_synced_set(
    readers: Sequence[SyncedSensorReader],
    *,
    max_skew_ms: float,
    deadline_ns: int,
    max_age_ms: float | None = None,
    clock_ns: Callable[[], int] = time.monotonic_ns,
) -> dict[str, SensorFrame]:
    """One frame per reader whose capture stamps all lie within ``max_skew_ms`` of each other.

    Starts from each reader's latest frame; while some frames are older than the newest by
    more than the skew, waits (until ``deadline_ns``) for those readers' next frames.

    Raises:
        ROSPerceptionStale: A reader has no fresh frame at all.
        ROSSyncError: No set within the skew could be made by the deadline; says which
            sensors lagged and the skew of the best set.
    """
    frames = {reader.sensor_id: reader.read_latest(max_age_ms) for reader in readers}
    by_id = {reader.sensor_id: reader for reader in readers}
    skew_ns = max_skew_ms * 1e6
    while True:
        newest = max(frame.stamp_ns for frame in frames.values())
        lagging = [sid for sid, frame in frames.items() if newest - frame.stamp_ns > skew_ns]
        if not lagging:
            return frames
        for sensor_id in lagging:
            if clock_ns() >= deadline_ns:
                spread = (newest - min(f.stamp_ns for f in frames.values())) / 1e6
                raise ROSSyncError(
                    f"no frame set within {max_skew_ms} ms by the deadline: {', '.join(sorted(lagging))} "
                    f"lag the newest frame (spread {spread:.1f} ms)",
                    skew_ms=spread,
                    lagging=tuple(sorted(lagging)),
                )
            try:
                frames[sensor_id] = by_id[sensor_id].read_synced(deadline_ns, newer_than_ns=frames[sensor_id].stamp_ns)
            except ROSPerceptionStale:  # the reader's own deadline passed: reported as a sync failure above
                continue
