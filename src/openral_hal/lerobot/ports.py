"""The serial ports of a LeRobot device, locked before its driver sends a byte and for as long as it runs.

LeRobot's buses open their ports themselves, inside ``connect()``. openral opens each port once
more first, only to hold an exclusive ``flock`` on it: a second runner on the same arm fails
before it writes anything. Once the driver has its own descriptor, the port is also made to
refuse other programs' ``open()`` (``TIOCEXCL``), as openral's own serial HAL does.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterable

from openral_core.errors import ROSHardwareError
from openral_hal.device_lock import device_busy_error, lock_device, refuse_other_opens, unlock_device


class PortLocks:
    """Exclusive locks on a device's serial ports; ``release`` gives them all back."""

    def __init__(self) -> None:
        self._held: dict[str, int] = {}

    def acquire(self, ports: Iterable[str]) -> None:
        """Lock every port, or none (what was taken is released when one fails).

        Raises:
            ROSHardwareError: A port does not exist, cannot be opened, or another process holds it.
        """
        try:
            for port in ports:
                if port not in self._held:
                    self._held[port] = _open_locked(port)
        except BaseException:
            self.release()
            raise

    def refuse_other_opens(self) -> None:
        """Make every held port refuse further ``open()``s (call once the driver has opened them)."""
        for fd in self._held.values():
            refuse_other_opens(fd)

    def release(self) -> None:
        """Unlock and close every held port. Idempotent; never raises."""
        held, self._held = self._held, {}
        for fd in held.values():
            unlock_device(fd)
            with contextlib.suppress(OSError):
                os.close(fd)


def _open_locked(port: str) -> int:
    try:
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        if exc.errno == errno.EBUSY:
            raise device_busy_error(port) from exc
        raise ROSHardwareError(
            f"cannot open {port}: {exc.strerror} (is the robot's USB adapter plugged in, and is the port "
            "readable by this user?)"
        ) from exc
    try:
        lock_device(fd, port, exclusive_open=False)
    except BaseException:
        os.close(fd)
        raise
    return fd
