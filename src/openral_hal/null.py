"""``NullHAL``: a robot with no physics and no I/O, for measuring the runner's own overhead.

``read_state`` reports the last commanded positions (clipped into the joint limits, as a
servo would), so a closed loop sees its commands take effect instantly. Each call does a
few list operations and builds one ``JointState``, so benchmark figures are the runner's.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from openral_core.actions import Action
from openral_core.config import validate_model
from openral_core.errors import ROSHardwareError
from openral_core.robot import RobotManifest
from openral_core.world import JointState
from openral_hal.joints import JointIndex, initial_positions


class NullHALParams(BaseModel):
    """Parameters of the ``null`` HAL.

    Attributes:
        initial_positions: Start position per joint name; unnamed joints start at 0 clipped into their limits.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    initial_positions: dict[str, float] = Field(default_factory=dict)


class NullHAL:
    """A HAL that echoes commands back as measurements.

    Args:
        manifest: The robot whose joints and limits to mirror.
        params: Validated as :class:`NullHALParams`.

    Raises:
        ROSConfigError: A wrong parameter key or an invalid initial position.
    """

    adapter = "null"

    def __init__(self, manifest: RobotManifest, params: Mapping[str, Any] | None = None) -> None:
        self.params = validate_model(
            NullHALParams, dict(params or {}), source="the null HAL", field_prefix="hal.params"
        )
        self.manifest = manifest
        self.robot_id = manifest.robot_id
        self.joint_names = manifest.joint_names
        self._index = JointIndex(self.robot_id, self.joint_names)
        self._lower = [j.lower for j in manifest.joints]
        self._upper = [j.upper for j in manifest.joints]
        self._positions = initial_positions(manifest, self.params.initial_positions)
        self._lock = threading.Lock()
        self._connected = False

    @property
    def is_connected(self) -> bool:
        """``True`` between ``connect()`` and ``disconnect()``."""
        return self._connected

    def connect(self) -> None:
        """Mark the robot connected; there is nothing to open."""
        self._connected = True

    def disconnect(self) -> None:
        """Mark the robot disconnected. Idempotent."""
        self._connected = False

    def read_state(self) -> JointState:
        """The last commanded positions, stamped now.

        Raises:
            ROSHardwareError: Not connected.
        """
        if not self._connected:
            raise ROSHardwareError(f"null HAL of '{self.robot_id}' is not connected; call connect() first")
        with self._lock:
            positions = list(self._positions)
        # Built without re-validation: names are the manifest's (unique) and positions are ours.
        return JointState.model_construct(
            names=list(self.joint_names),
            positions=positions,
            velocities=None,
            efforts=None,
            stamp_ns=time.monotonic_ns(),
        )

    def send_action(self, action: Action) -> None:
        """Take ``action.first`` as the new positions, clipped into the joint limits.

        Raises:
            ROSConfigError: Unknown joint name or unsupported control mode.
            ROSSafetyViolation: A non-finite value.
            ROSHardwareError: Not connected.
        """
        if not self._connected:
            raise ROSHardwareError(f"null HAL of '{self.robot_id}' is not connected; call connect() first")
        indices, values = self._index.targets(action, adapter=self.adapter)
        lower, upper = self._lower, self._upper
        with self._lock:
            for i, value in zip(indices, values, strict=True):
                self._positions[i] = min(max(value, lower[i]), upper[i])

    def estop(self) -> None:
        """Hold: the echoed positions are already the measured ones, so nothing changes."""
