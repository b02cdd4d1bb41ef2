"""``lerobot_robot``: any robot LeRobot drives, by its registered ``type``, as an openral HAL.

.. code-block:: yaml

    hal:
      robot_id: so101_follower
      adapter: lerobot_robot
      params:
        type: so101_follower          # LeRobot's robot type (its own or a lerobot_robot_* plugin's)
        port: /dev/ttyACM0            # the rest is LeRobot's config for that type, as lerobot-record takes it
        id: my_follower               # whose calibration file (lerobot-calibrate --robot.id)

LeRobot's own driver code runs the robot (its buses, handshake, motor configuration,
normalisation with the calibration); openral runs the loop around it. What openral adds:

* **Units.** Joints come out in the manifest's order and radians; LeRobot's per-motor
  conventions (degrees, -100..100, a 0..100 gripper) are converted both ways by the conversion
  the ``lerobot_policy`` skill uses (:mod:`openral_hal.lerobot.units`).
* **No camera inside a tick.** ``read_state`` reads the motors only; the robot's cameras are
  openral sensors (backend ``lerobot_camera``) with their own capture threads and stamps.
* **No prompt, no jump.** It connects with ``calibrate=False``: a missing calibration file is a
  configuration error, a file the motors disagree with is written to them. Before torque comes
  on, every goal becomes the present position, so the arm holds where it is.
* **One owner, limp on stop.** Every serial port is locked before the driver opens it, and every
  stop path (``disconnect``, a failed connect, a forced stop while a read is stuck) switches torque
  off on every bus, unless the arm's LeRobot config says ``disable_torque_on_disconnect: false``
  (then it holds, as LeRobot's own disconnect would leave it).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Mapping
from contextlib import suppress
from typing import Any, Final

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core.actions import Action
from openral_core.config import validate_model
from openral_core.errors import ROSConfigError, ROSHardwareError
from openral_core.robot import RobotManifest
from openral_core.world import JointState
from openral_hal.feetech import protocol as feetech
from openral_hal.feetech.protocol import Register
from openral_hal.joints import JointIndex
from openral_hal.lerobot.calibration import require_calibration, write_calibration_where_it_differs
from openral_hal.lerobot.device_config import build_device_config, make_device, require_lerobot
from openral_hal.lerobot.motors import POSITION_SUFFIX, motor_buses, position_norms
from openral_hal.lerobot.ports import PortLocks
from openral_hal.lerobot.units import JointUnits, MotorNorm, UnitConversion, arm_norms

ADAPTER: Final = "lerobot_robot"
FIELD: Final = "hal.params"
_TORQUE_OFF_RETRIES: Final = 5

_log = structlog.get_logger(__name__)


class LeRobotRobotOptions(BaseModel):
    """openral's own keys beside LeRobot's config (everything else in ``hal.params`` is LeRobot's).

    Attributes:
        type: LeRobot's robot type.
        joint_units: The convention of joints LeRobot's buses do not describe (a robot without a
            ``MotorsBus``); joints on a bus use the bus's own.
    """

    model_config = ConfigDict(extra="ignore", frozen=True)

    type: str = Field(min_length=1)
    joint_units: JointUnits | None = None


class LeRobotRobotHAL:
    """A LeRobot robot under openral's loop.

    Args:
        manifest: The robot; its joints are LeRobot's ``<joint>.pos`` action features, in any order.
        params: ``type``, optionally ``joint_units``, and LeRobot's config for that type.

    Raises:
        ROSConfigError: An unknown type, a key LeRobot's config refuses, cameras given to the robot,
            joints that do not match the robot's, or a missing calibration file.
    """

    adapter = ADAPTER

    def __init__(self, manifest: RobotManifest, params: Mapping[str, Any] | None = None) -> None:
        require_lerobot(f"the {ADAPTER} HAL")
        given = dict(params or {})
        options = validate_model(LeRobotRobotOptions, given, source=f"the {ADAPTER} HAL", field_prefix=FIELD)
        lerobot_params = {k: v for k, v in given.items() if k not in LeRobotRobotOptions.model_fields}
        self.manifest = manifest
        self.robot_id = manifest.robot_id
        self.joint_names = manifest.joint_names
        self.type_name = options.type
        self.config = build_device_config("robot", options.type, lerobot_params, field=FIELD)
        _refuse_cameras(self.config, options.type)
        self.robot = make_device("robot", self.config, field=FIELD)
        self.keys = _position_keys(self.robot, manifest, options.type)
        self.units = UnitConversion(manifest, _norms(self.robot, manifest, self.keys, options.joint_units))
        require_calibration(self.robot, kind="robot", type_name=options.type, params=lerobot_params, field=FIELD)
        self._index = JointIndex(self.robot_id, self.joint_names)
        self._lower = np.array([j.lower for j in manifest.joints])
        self._upper = np.array([j.upper for j in manifest.joints])
        self._targets = np.zeros(len(self.joint_names))
        self._locks = PortLocks()
        self._lock = threading.RLock()
        self._connected = False

    @property
    def ports(self) -> list[str]:
        """The serial ports of the robot's buses."""
        return [found.port for found in motor_buses(self.robot)]

    @property
    def is_connected(self) -> bool:
        """``True`` between ``connect()`` and ``disconnect()`` while LeRobot reports the robot connected."""
        return self._connected and bool(self.robot.is_connected)

    def connect(self) -> None:
        """Lock the ports, connect through LeRobot (no prompt), apply the calibration, hold the pose.

        Raises:
            ROSHardwareError: A port is missing or held by another process, or LeRobot's connect
                failed (its message kept); torque is off and every port released.
        """
        with self._lock:
            if self._connected:
                return
            self._locks.acquire(self.ports)
            try:
                for found in motor_buses(self.robot):
                    _hold_before_torque(found.bus)
                self.robot.connect(calibrate=False)
                self._locks.refuse_other_opens()
                written = write_calibration_where_it_differs(self.robot)
                if written:
                    _log.info("lerobot_calibration_written", robot=self.robot_id, arms=written)
                self._targets = self._read_radians()
            except ROSHardwareError:
                self._stop_robot()
                raise
            except Exception as exc:
                self._stop_robot()
                raise _hardware_error(f"robot '{self.robot_id}' ({self.type_name}) failed to connect", exc) from exc
            self._connected = True

    def disconnect(self) -> None:
        """Torque off on every bus, close the ports, release the locks. Idempotent; never raises.

        Safe from another thread while a transaction is stuck (a forced stop): a Feetech bus gets a
        torque-off broadcast at once, without waiting for the bus, before the orderly shutdown.
        """
        if self._connected:
            for found in motor_buses(self.robot):
                if _torque_off_on_stop(found.owner):
                    _broadcast_torque_off(found.bus)
        with self._lock:
            self._connected = False
            self._stop_robot()

    def read_state(self) -> JointState:
        """Joint positions in radians (the motors only, no camera), stamped before the read.

        Raises:
            ROSHardwareError: Not connected, or LeRobot's read failed.
        """
        with self._lock:
            self._require_connected()
            stamp = time.monotonic_ns()
            positions = self._read_radians()
        return JointState.model_construct(
            names=list(self.joint_names), positions=positions.tolist(), velocities=None, efforts=None, stamp_ns=stamp
        )

    def send_action(self, action: Action) -> None:
        """Row 0 as goal positions, clipped to the manifest's limits, in LeRobot's units.

        Raises:
            ROSConfigError: Unknown joint or unsupported control mode.
            ROSSafetyViolation: A non-finite value.
            ROSHardwareError: Not connected, or LeRobot's write failed.
        """
        indices, values = self._index.targets(action, adapter=ADAPTER)
        with self._lock:
            self._require_connected()
            targets = self._targets.copy()
            targets[list(indices)] = values
            targets = np.clip(targets, self._lower, self._upper)
            self._write_radians(targets)
            self._targets = targets

    def estop(self) -> None:
        """Hold: every goal becomes the present position.

        Raises:
            ROSHardwareError: Not connected, or the hold could not be written.
        """
        with self._lock:
            self._require_connected()
            present = self._read_radians()
            self._write_radians(present)
            self._targets = present

    # -- internals ------------------------------------------------------------------------------

    def _read_radians(self) -> np.ndarray:
        try:
            observation = self.robot.get_observation()
            values = np.array([float(observation[key]) for key in self.keys])
        except Exception as exc:
            raise _hardware_error(f"reading robot '{self.robot_id}' failed", exc) from exc
        radians: np.ndarray = self.units.to_radians(values)
        return radians

    def _write_radians(self, radians: np.ndarray) -> None:
        values = self.units.to_policy(radians)
        try:
            self.robot.send_action({key: float(v) for key, v in zip(self.keys, values, strict=True)})
        except Exception as exc:
            raise _hardware_error(f"commanding robot '{self.robot_id}' failed", exc) from exc

    def _require_connected(self) -> None:
        if not self._connected:
            raise ROSHardwareError(f"{ADAPTER} HAL of '{self.robot_id}' is not connected; call connect() first")

    def _stop_robot(self) -> None:
        """Torque off on every bus, then LeRobot's disconnect; whatever fails, the ports are released."""
        for found in motor_buses(self.robot):
            if found.bus.is_connected and _torque_off_on_stop(found.owner):
                with suppress(Exception):
                    found.bus.disable_torque(num_retry=_TORQUE_OFF_RETRIES)
        with suppress(Exception):
            if self.robot.is_connected:
                self.robot.disconnect()
        for found in motor_buses(self.robot):
            with suppress(Exception):
                if found.bus.is_connected:
                    found.bus.port_handler.closePort()
        self._locks.release()


def _refuse_cameras(config: Any, type_name: str) -> None:
    """A camera read inside the robot's observation would put its frame time into every tick."""
    cameras = dict(getattr(config, "cameras", None) or {})
    for attribute in ("left_arm_config", "right_arm_config"):
        cameras.update(getattr(getattr(config, attribute, None), "cameras", None) or {})
    if cameras:
        blocks = "; ".join(_sensor_block(name, camera) for name, camera in sorted(cameras.items()))
        raise ROSConfigError(
            f"the robot's cameras ({', '.join(sorted(cameras))}) run as openral sensors, not inside its reads",
            field=f"{FIELD}.cameras",
            hint=f"move them under sensors: {blocks}",
        )


def _sensor_block(name: str, camera: Any) -> str:
    """The ``sensors:`` entry that runs one of a LeRobot robot's cameras on openral's capture thread."""
    sizes = {key: getattr(camera, key, None) for key in ("width", "height", "fps")}
    keys = {
        f.name: getattr(camera, f.name)
        for f in dataclasses.fields(camera)
        if f.name not in sizes and getattr(camera, f.name) != f.default and not callable(getattr(camera, f.name))
    }
    params = ", ".join([f"type: {getattr(camera, 'type', '?')}", *(f"{k}: {_plain(v)}" for k, v in keys.items())])
    fields = "".join(f", {key}: {value}" for key, value in sizes.items() if value is not None)
    return f"- {{sensor_id: {name}, backend: lerobot_camera{fields}, backend_params: {{{params}}}}}"


def _plain(value: Any) -> Any:
    return getattr(value, "value", value)


def _position_keys(robot: Any, manifest: RobotManifest, type_name: str) -> list[str]:
    """LeRobot's ``<joint>.pos`` key of each manifest joint, checked against the robot's features both ways."""
    features = dict(robot.action_features)
    positions = {key.removesuffix(POSITION_SUFFIX) for key in features if key.endswith(POSITION_SUFFIX)}
    other = sorted(key for key in features if not key.endswith(POSITION_SUFFIX))
    missing = [name for name in manifest.joint_names if name not in positions]
    extra = sorted(positions - set(manifest.joint_names))
    if missing or extra or other:
        parts = []
        if missing:
            parts.append(f"LeRobot's '{type_name}' has no joint {', '.join(missing)}")
        if extra:
            parts.append(f"the manifest lacks {', '.join(extra)}")
        if other:
            parts.append(f"actions other than joint positions ({', '.join(other)}) are not driven")
        raise ROSConfigError(
            f"robot '{manifest.robot_id}' does not match LeRobot's '{type_name}': {'; '.join(parts)}",
            field="hal.robot_id",
            hint=f"use a manifest whose joints are {', '.join(sorted(positions))}",
        )
    return [f"{name}{POSITION_SUFFIX}" for name in manifest.joint_names]


def _norms(robot: Any, manifest: RobotManifest, keys: list[str], units: JointUnits | None) -> list[MotorNorm]:
    """Each joint's convention: its bus motor's, else the deployment's ``joint_units``."""
    on_bus = position_norms(robot)
    fallback = arm_norms(manifest, units) if units is not None else None
    norms: list[MotorNorm] = []
    for i, key in enumerate(keys):
        if key in on_bus:
            norms.append(on_bus[key])
        elif fallback is not None:
            norms.append(fallback[i])
        else:
            raise ROSConfigError(
                f"joint '{manifest.joint_names[i]}' is on no LeRobot motor bus, so its units are unknown",
                field=f"{FIELD}.joint_units",
                hint="say them: radians, degrees or range",
            )
    return norms


def _hold_before_torque(bus: Any) -> None:
    """Make every torque-on of ``bus`` first set each goal to the present position (no jump to a stale goal)."""
    if getattr(bus, "_openral_holds", False):
        return
    enable: Callable[..., None] = bus.enable_torque

    def enable_holding(motors: Any = None, num_retry: int = 0) -> None:
        present = bus.sync_read("Present_Position", normalize=False, num_retry=num_retry)
        bus.sync_write("Goal_Position", present, normalize=False)
        enable(motors, num_retry=num_retry)

    bus.enable_torque = enable_holding
    bus._openral_holds = True


def _torque_off_on_stop(arm: Any) -> bool:
    """An arm goes limp when the run stops unless its LeRobot config says ``disable_torque_on_disconnect: false``."""
    return bool(getattr(getattr(arm, "config", None), "disable_torque_on_disconnect", True))


def _broadcast_torque_off(bus: Any) -> None:
    """One Feetech broadcast write of torque off straight onto the port: no reply, no lock, never raises."""
    from lerobot.motors.feetech import FeetechMotorsBus  # noqa: PLC0415  (the extra, imported with the robot)

    serial_port = getattr(getattr(bus, "port_handler", None), "ser", None)
    if serial_port is None or not isinstance(bus, FeetechMotorsBus):
        return
    with suppress(Exception):
        serial_port.write(feetech.write_packet(feetech.BROADCAST_ID, Register.TORQUE_ENABLE, b"\x00"))
        serial_port.flush()


def _hardware_error(what: str, exc: Exception) -> ROSHardwareError:
    detail = " ".join(str(exc).split()) or type(exc).__name__
    return ROSHardwareError(f"{what}: {detail}")
