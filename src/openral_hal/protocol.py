"""The ``HAL`` seam: the few calls the runner makes on a robot, real or simulated.

Every adapter (the MuJoCo twin, the null HAL, a serial arm, the recording fake) is a
plugin in the ``openral.hals`` entry-point group and is constructed the same way::

    hal = Adapter(manifest, params)   # manifest: RobotManifest, params: Mapping[str, Any]

The adapter validates ``params`` with its own pydantic model (``extra="forbid"``) through
``openral_core.config.validate_model``, so a wrong key is a ``ROSConfigError`` that names the
key and lists the allowed ones. Construction does no I/O that must be undone: opening the
device is ``connect()``'s job, so a failed start-up has nothing to roll back.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any, Protocol, runtime_checkable

from openral_core.actions import Action
from openral_core.robot import RobotManifest
from openral_core.world import JointState


@runtime_checkable
class HAL(Protocol):
    """A robot the runner can read and command.

    Attributes:
        robot_id: Id of the robot manifest this HAL drives (``so101_follower``, ...).
        joint_names: The robot's joints in manifest order; ``read_state`` reports them in this order.

    Calls may come from different threads (the tick thread, a signal handler asking for an
    e-stop); an adapter makes ``estop`` safe to call while another call is in progress.
    """

    robot_id: str
    joint_names: list[str]

    @property
    def is_connected(self) -> bool:
        """``True`` between a successful ``connect()`` and ``disconnect()`` while the robot responds."""
        ...

    def connect(self) -> None:
        """Open the robot (bus, physics thread, ...). Calling it when already connected does nothing.

        Raises:
            ROSHardwareError: The robot cannot be opened; nothing is left open.
        """
        ...

    def disconnect(self) -> None:
        """Release the robot. Idempotent: safe to call twice or without ``connect()``."""
        ...

    def read_state(self) -> JointState:
        """Measured joint positions (and velocities where the robot reports them), in ``joint_names`` order.

        ``stamp_ns`` is the measurement time on ``time.monotonic_ns()``.

        Raises:
            ROSHardwareError: Not connected, or the read failed.
        """
        ...

    def send_action(self, action: Action) -> None:
        """Apply ``action.first`` (row 0) as the new joint targets.

        Values are matched to joints by ``action.joint_names``; joints the action does not name
        keep their previous target. Targets outside the robot's command range are clipped to it.

        Raises:
            ROSConfigError: The action names a joint the robot lacks, or uses a control mode
                the adapter does not support. Nothing is applied.
            ROSSafetyViolation: A value is NaN or infinite (``check_name="non_finite"``). Nothing is applied.
            ROSHardwareError: Not connected, or the write failed.
        """
        ...

    def estop(self) -> None:
        """Hold the robot where it is now: every joint's target becomes its measured position.

        Works mid-run, from any thread, and never raises because the robot is moving. It does
        not latch: a later ``send_action`` moves the robot again, so the caller stops sending.

        Raises:
            ROSHardwareError: The hold command could not be delivered.
        """
        ...


class HALPlugin(Protocol):
    """What the ``openral.hals`` group holds: an adapter class, built as ``Adapter(manifest, params)``."""

    def __call__(self, manifest: RobotManifest, params: Mapping[str, Any]) -> HAL:
        """Build an unconnected HAL for ``manifest``, validating ``params`` (the deployment's ``hal.params``).

        Raises:
            ROSConfigError: A wrong or missing parameter, named as ``hal.params.<key>``.
        """
        ...


@contextmanager
def connected(hal: HAL) -> Iterator[HAL]:
    """Connect ``hal`` for the duration of a ``with`` block and always disconnect it afterwards."""
    hal.connect()
    try:
        yield hal
    finally:
        hal.disconnect()
