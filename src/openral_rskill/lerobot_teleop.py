"""``lerobot_teleop``: any LeRobot leader device (SO-100/101, Koch, bimanual SO, ...) drives the follower.

.. code-block:: yaml

    vla:                      # or a deployment's takeover: block, or openral record's skill
      id: lerobot_teleop
      params: {type: so101_leader, port: /dev/ttyACM1, id: my_leader}

``params`` are ``type`` and LeRobot's own keys for that teleoperator, decoded by its own config
class, and the device is built by LeRobot's factory when the skill is built: ``openral validate``
refuses what connecting would (an unknown key or type, a missing calibration file, a device whose
joints are not the follower's); a leader arm's port opens only on activation. It connects then
without calibrating: calibration is LeRobot's interactive ``lerobot-calibrate``, done once; a
calibration file the motors do not hold yet is written to them, as LeRobot's own prompt does on
ENTER. Each step reads ``get_action()``: ``<joint>.pos`` keys (``left_``/``right_`` prefixed for a
bimanual device) are the follower's joints by name, converted from the motors' LeRobot conventions
to the manifest's radians by the same conversion as LeRobot robots under openral, so a leader's
0..100 gripper spans the follower jaw's limits exactly as LeRobot's follower would.

A gamepad or ``keyboard_ee`` gives end-effector deltas and a gripper action instead: each step
moves the gripper from the last target (the measured pose at first) through the manifest's own
kinematic chain (:mod:`openral_rskill.ee_deltas`). A device that gives neither joint positions nor
end-effector deltas (a rover's velocities, raw key presses) is refused.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Mapping
from typing import Any, Protocol, Self

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core.actions import Action, ControlMode
from openral_core.config import validate_model
from openral_core.errors import ROSConfigError
from openral_core.robot import JointKind, RobotManifest
from openral_core.skills import RSkillInfo
from openral_core.world import WorldState
from openral_hal.lerobot.calibration import require_calibration, write_calibration_where_it_differs
from openral_hal.lerobot.device_config import build_device_config, known_types, make_device, require_lerobot
from openral_hal.lerobot.motors import POSITION_SUFFIX, motor_buses, position_norms
from openral_hal.lerobot.ports import PortLocks
from openral_hal.lerobot.units import UnitConversion
from openral_rskill.base import RSkillBase
from openral_rskill.ee_deltas import AXES, EndEffectorDeltas

SKILL_ID = "lerobot_teleop"
FIELD = "vla.params"
_LOG = structlog.get_logger(__name__)


class TeleopOptions(BaseModel):
    """openral's own keys beside the teleoperator's LeRobot config.

    Attributes:
        type: LeRobot's teleoperator type.
        ee_step_m: For a device that gives end-effector deltas (gamepad, ``keyboard_ee``): metres
            the gripper moves per step for a full deflection on one axis.
        gripper_step_rad: For such a device: radians the jaw moves per step on open or close
            (default: a quarter of its velocity limit).
    """

    model_config = ConfigDict(extra="ignore", frozen=True, allow_inf_nan=False)

    type: str = Field(min_length=1)
    ee_step_m: float = Field(default=0.004, gt=0, le=0.05)
    gripper_step_rad: float | None = Field(default=None, gt=0, le=1.0)


class ReadingMap(Protocol):
    """What a teleoperator's reading means as the follower's joint targets."""

    def reset(self) -> None:
        """Forget any motion integrated so far (the next reading starts from the measured pose)."""

    def targets(self, reading: Mapping[str, Any], world_state: WorldState) -> np.ndarray:
        """The follower's joint targets, in the manifest's order and radians."""


class JointPositionMap:
    """A leader arm: each follower joint is the leader's motor of that name, in radians."""

    def __init__(self, keys: list[str], conversion: UnitConversion) -> None:
        self.keys = keys
        self.conversion = conversion

    def reset(self) -> None:
        """Nothing integrates: every reading is a whole pose."""

    def targets(self, reading: Mapping[str, Any], world_state: WorldState) -> np.ndarray:
        values = np.fromiter((reading[key] for key in self.keys), dtype=np.float64, count=len(self.keys))
        radians: np.ndarray = self.conversion.to_radians(values)
        return radians


class EndEffectorMap:
    """A gamepad or keyboard: each reading moves the gripper from the last target (the measured pose at first)."""

    def __init__(self, robot: RobotManifest, deltas: EndEffectorDeltas) -> None:
        self.robot = robot
        self.deltas = deltas
        self._target: np.ndarray | None = None

    def reset(self) -> None:
        self._target = None

    def targets(self, reading: Mapping[str, Any], world_state: WorldState) -> np.ndarray:
        if self._target is None:
            self._target = _measured(self.robot, world_state)
        self._target = self.deltas.step(self._target, reading)
        return self._target


class LeRobotTeleopSkill(RSkillBase):
    """Commands the follower to the joint positions a LeRobot teleoperator reads.

    Args:
        robot: The follower.
        teleoperator: LeRobot's teleoperator, built and not connected; its calibration files exist.
        type_name: Its LeRobot type, for messages.
        mapping: What its readings mean as the follower's joint targets.
    """

    INFO = RSkillInfo(
        skill_id=SKILL_ID,
        name="LeRobot teleoperator",
        version="1.0.0",
        license="Apache-2.0",
        control_mode=ControlMode.JOINT_POSITION,
        chunk_size=1,
        description="Commands the follower to the joint positions of a LeRobot leader device.",
    )

    def __init__(self, robot: RobotManifest, teleoperator: Any, *, type_name: str, mapping: ReadingMap) -> None:
        super().__init__()
        self.robot = robot
        self.teleoperator = teleoperator
        self.type_name = type_name
        self.mapping = mapping
        self._names = robot.joint_names
        self._ports = PortLocks()

    @classmethod
    def from_config(cls, params: Mapping[str, Any], *, robot: RobotManifest, rate_hz: float) -> Self:
        """Build the teleoperator from ``type`` and LeRobot's keys; nothing is opened until activation.

        Raises:
            ROSConfigError: An unknown type or key, a calibration file that is missing or does not
                match the motors, a device that gives no joint positions, or joints that are not the
                follower's.
            ROSDependencyMissing: The ``lerobot`` extra is not installed.
        """
        require_lerobot(f"the {SKILL_ID} skill")
        device_params = {k: v for k, v in params.items() if k not in TeleopOptions.model_fields}
        type_name = params.get("type")
        if not isinstance(type_name, str) or not type_name:
            raise ROSConfigError(
                "a LeRobot teleoperator needs its 'type'",
                field=f"{FIELD}.type",
                hint=f"known: {', '.join(known_types('teleoperator'))}",
            )
        options = validate_model(TeleopOptions, dict(params), source=f"the {SKILL_ID} skill", field_prefix=FIELD)
        config = build_device_config("teleoperator", type_name, device_params, field=FIELD)
        teleoperator = make_device("teleoperator", config, field=FIELD)
        mapping = _reading_map(teleoperator, type_name, robot, options, rate_hz)
        require_calibration(teleoperator, kind="teleop", type_name=type_name, params=device_params, field=FIELD)
        return cls(robot, teleoperator, type_name=type_name, mapping=mapping)

    @property
    def info(self) -> RSkillInfo:
        """Identity of the ``lerobot_teleop`` skill."""
        return self.INFO

    def _on_reset(self) -> None:
        self.mapping.reset()

    def _on_activate(self) -> None:
        self.mapping.reset()
        try:
            self._ports.acquire(found.port for found in motor_buses(self.teleoperator))
            self.teleoperator.connect(calibrate=False)
            self._ports.refuse_other_opens()
            written = write_calibration_where_it_differs(self.teleoperator)
            if written:
                _LOG.info("lerobot_calibration_written", teleoperator=self.type_name, arms=written)
        except BaseException:
            self._release()
            raise

    def _on_deactivate(self) -> None:
        self._release()

    def _on_shutdown(self) -> None:
        self._release()

    def _release(self) -> None:
        """Disconnect the teleoperator, and any of its buses a failed connection left open; free its ports."""
        try:
            if self.teleoperator.is_connected:
                self.teleoperator.disconnect()
        finally:
            for found in motor_buses(self.teleoperator):
                if found.bus.is_connected:
                    with contextlib.suppress(Exception):  # best effort after a failure already raised
                        found.bus.disconnect(disable_torque=False)
            self._ports.release()

    def _step_impl(self, world_state: WorldState) -> Action:
        stamp = time.monotonic_ns()
        targets = self.mapping.targets(self.teleoperator.get_action(), world_state)
        return Action(
            control_mode=ControlMode.JOINT_POSITION,
            joint_names=self._names,
            targets=[targets.tolist()],
            stamp_ns=stamp,
            skill_id=SKILL_ID,
        )


def _reading_map(
    teleoperator: Any, type_name: str, robot: RobotManifest, options: TeleopOptions, rate_hz: float
) -> ReadingMap:
    """Joint positions for a leader arm; end-effector motion for a device that gives ``delta_x/y/z``."""
    names = _action_names(teleoperator)
    if set(AXES) <= set(names):
        jaws = [j for j in robot.joints if j.kind is JointKind.GRIPPER]
        gripper_step = options.gripper_step_rad or (jaws[0].velocity_limit / 4 / rate_hz if jaws else 0.0)
        try:
            deltas = EndEffectorDeltas(robot, step_m=options.ee_step_m, gripper_step_rad=gripper_step, rate_hz=rate_hz)
        except ROSConfigError as exc:
            raise ROSConfigError(
                f"LeRobot's '{type_name}' teleoperator moves the end effector, and '{robot.robot_id}' has no "
                f"kinematic chain to turn that into joint targets: {exc}",
                field=f"{FIELD}.type",
                hint="a manifest with a mujoco model and its ee_site, or a leader arm",
            ) from exc
        return EndEffectorMap(robot, deltas)
    keys, norms = _joint_keys(teleoperator, type_name, robot)
    return JointPositionMap(keys, UnitConversion(robot, norms))


def _action_names(teleoperator: Any) -> list[str]:
    """The keys of the teleoperator's readings (a gamepad declares them under ``names``)."""
    features = dict(teleoperator.action_features)
    named = features.get("names")
    return list(named) if isinstance(named, Mapping) and "shape" in features else list(features)


def _measured(robot: RobotManifest, world_state: WorldState) -> np.ndarray:
    """The measured joint positions in the manifest's order (where an end-effector motion starts from)."""
    state = world_state.joint_state
    if state is None:
        return np.array([min(max(0.0, j.lower), j.upper) for j in robot.joints])
    by_name = dict(zip(state.names, state.positions, strict=True))
    return np.array([by_name[name] for name in robot.joint_names], dtype=np.float64)


def _joint_keys(teleoperator: Any, type_name: str, robot: RobotManifest) -> tuple[list[str], list[Any]]:
    """The action key and LeRobot convention of each follower joint, in the manifest's order."""
    features = list(teleoperator.action_features)
    norms = position_norms(teleoperator)
    not_positions = [key for key in features if key not in norms]
    if not features or not_positions:
        raise ROSConfigError(
            f"LeRobot's '{type_name}' teleoperator gives {not_positions or 'nothing'}, not the joint positions "
            f"('<joint>{POSITION_SUFFIX}' of motors on a bus) that command a joint-position follower",
            field=f"{FIELD}.type",
            hint="use a leader arm with the follower's joints (so101_leader, koch_leader, bi_so_leader, ...)",
        )
    by_joint = {key.removesuffix(POSITION_SUFFIX): key for key in features}
    extra = [joint for joint in by_joint if joint not in robot.joint_names]
    missing = [joint for joint in robot.joint_names if joint not in by_joint]
    if extra or missing:
        parts = [f"moves {extra}, which '{robot.robot_id}' does not have"] if extra else []
        parts += [f"does not give '{robot.robot_id}' joint(s) {missing}"] if missing else []
        raise ROSConfigError(
            f"LeRobot's '{type_name}' teleoperator {' and '.join(parts)}",
            field=f"{FIELD}.type",
            hint=f"its joints: {', '.join(by_joint)}; the follower's: {', '.join(robot.joint_names)}",
        )
    keys = [by_joint[joint] for joint in robot.joint_names]
    return keys, [norms[key] for key in keys]
