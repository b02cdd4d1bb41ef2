"""``RecordingHAL``: a fake robot for runner tests, with no hardware, no physics and no sleeping.

It keeps to the ``HAL`` contract (unknown joints, non-finite values and calls before
``connect()`` fail exactly as on a real adapter), records every call, and fails on cue so a
test can drive the runner's fault policies.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Sequence
from typing import Any

from openral_core.actions import Action
from openral_core.errors import ROSHardwareError
from openral_core.robot import RobotManifest
from openral_core.world import JointState
from openral_hal.joints import JointIndex
from openral_hal.manifests import load_robot_manifest


class RecordingHAL:
    """A HAL that records what it is told and echoes the last command as its state.

    Args:
        joints: Joint names, or a manifest (whose ``robot_id`` and joint names are used).
        robot_id: Id reported when ``joints`` is a list of names.
        initial_positions: Start positions in joint order; zeros by default.
        fail_connect: Raised by every ``connect()`` while set (assign ``None`` to heal).
        fail_read_on: 0-based indices of ``read_state`` calls that raise ``ROSHardwareError``.
        fail_send_on: 0-based indices of ``send_action`` calls that raise ``ROSHardwareError``
            (the action is still recorded in ``attempted`` but not applied).
        on_send: Called with each action after it is applied (a test advances a fake clock here).
        clock_ns: Source of ``JointState.stamp_ns``; ``time.monotonic_ns`` by default.

    Attributes:
        sent: Every applied action, in order.
        attempted: Every action passed to ``send_action`` that reached the fault check.
        calls: Names of the HAL methods called, in order (``connect``, ``read_state``, ...).
    """

    adapter = "recording"

    def __init__(
        self,
        joints: Sequence[str] | RobotManifest = ("j0", "j1", "j2"),
        *,
        robot_id: str = "recording",
        initial_positions: Sequence[float] | None = None,
        fail_connect: BaseException | None = None,
        fail_read_on: Collection[int] = (),
        fail_send_on: Collection[int] = (),
        on_send: Callable[[Action], Any] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if isinstance(joints, RobotManifest):
            self.robot_id = joints.robot_id
            self.joint_names = joints.joint_names
        else:
            self.robot_id = robot_id
            self.joint_names = list(joints)
        self._index = JointIndex(self.robot_id, self.joint_names)
        n = len(self.joint_names)
        self.positions: list[float] = list(initial_positions) if initial_positions is not None else [0.0] * n
        if len(self.positions) != n:
            raise ValueError(f"initial_positions has {len(self.positions)} values for {n} joints")
        self.fail_connect = fail_connect
        self.fail_read_on = set(fail_read_on)
        self.fail_send_on = set(fail_send_on)
        self.on_send = on_send
        self.clock_ns = clock_ns
        self.sent: list[Action] = []
        self.attempted: list[Action] = []
        self.calls: list[str] = []
        self.connect_calls = 0
        self.disconnect_calls = 0
        self.read_calls = 0
        self.estop_calls = 0
        self._connected = False

    @classmethod
    def for_robot(cls, robot_id: str, **options: Any) -> RecordingHAL:
        """A recording HAL with the joints of a shipped robot manifest."""
        return cls(load_robot_manifest(robot_id), **options)

    @property
    def is_connected(self) -> bool:
        """``True`` between a successful ``connect()`` and ``disconnect()``."""
        return self._connected

    def connect(self) -> None:
        """Count the call; raise ``fail_connect`` when it is set."""
        self.calls.append("connect")
        self.connect_calls += 1
        if self.fail_connect is not None:
            raise self.fail_connect
        self._connected = True

    def disconnect(self) -> None:
        """Count the call and disconnect. Idempotent."""
        self.calls.append("disconnect")
        self.disconnect_calls += 1
        self._connected = False

    def read_state(self) -> JointState:
        """The last commanded positions, unless this call's index is in ``fail_read_on``.

        Raises:
            ROSHardwareError: Not connected, or a scripted read failure.
        """
        self.calls.append("read_state")
        call = self.read_calls
        self.read_calls += 1
        self._require_connected()
        if call in self.fail_read_on:
            raise ROSHardwareError(f"scripted read_state failure on call {call} of '{self.robot_id}'")
        return JointState(names=list(self.joint_names), positions=list(self.positions), stamp_ns=self.clock_ns())

    def send_action(self, action: Action) -> None:
        """Check ``action`` like a real adapter, record it, apply row 0 and call ``on_send``.

        Raises:
            ROSConfigError: Unknown joint name or unsupported control mode.
            ROSSafetyViolation: A non-finite value.
            ROSHardwareError: Not connected, or a scripted send failure.
        """
        self.calls.append("send_action")
        self._require_connected()
        indices, values = self._index.targets(action, adapter=self.adapter)
        call = len(self.attempted)
        self.attempted.append(action)
        if call in self.fail_send_on:
            raise ROSHardwareError(f"scripted send_action failure on call {call} of '{self.robot_id}'")
        for i, value in zip(indices, values, strict=True):
            self.positions[i] = value
        self.sent.append(action)
        if self.on_send is not None:
            self.on_send(action)

    def estop(self) -> None:
        """Count the call; the echoed positions already hold still."""
        self.calls.append("estop")
        self.estop_calls += 1

    def _require_connected(self) -> None:
        if not self._connected:
            raise ROSHardwareError(f"recording HAL of '{self.robot_id}' is not connected; call connect() first")
