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

A teleoperator that gives no joint positions (a gamepad's or keyboard's end-effector deltas, key
presses) is refused: a joint-position follower has no principled use for them.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Mapping
from typing import Any, Self

import numpy as np
import structlog

from openral_core.actions import Action, ControlMode
from openral_core.errors import ROSConfigError
from openral_core.robot import RobotManifest
from openral_core.skills import RSkillInfo
from openral_core.world import WorldState
from openral_hal.lerobot.calibration import require_calibration, write_calibration_where_it_differs
from openral_hal.lerobot.device_config import build_device_config, known_types, make_device, require_lerobot
from openral_hal.lerobot.motors import POSITION_SUFFIX, motor_buses, position_norms
from openral_hal.lerobot.units import UnitConversion
from openral_rskill.base import RSkillBase

SKILL_ID = "lerobot_teleop"
FIELD = "vla.params"
_LOG = structlog.get_logger(__name__)


class LeRobotTeleopSkill(RSkillBase):
    """Commands the follower to the joint positions a LeRobot teleoperator reads.

    Args:
        robot: The follower.
        teleoperator: LeRobot's teleoperator, built and not connected; its calibration files exist.
        type_name: Its LeRobot type, for messages.
        keys: The teleoperator's action key of each follower joint, in the manifest's order.
        conversion: From those keys' LeRobot conventions to the manifest's radians.
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

    def __init__(
        self,
        robot: RobotManifest,
        teleoperator: Any,
        *,
        type_name: str,
        keys: list[str],
        conversion: UnitConversion,
    ) -> None:
        super().__init__()
        self.robot = robot
        self.teleoperator = teleoperator
        self.type_name = type_name
        self.keys = keys
        self.conversion = conversion
        self._names = robot.joint_names

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
        device_params = dict(params)
        type_name = device_params.pop("type", None)
        if not isinstance(type_name, str) or not type_name:
            raise ROSConfigError(
                "a LeRobot teleoperator needs its 'type'",
                field=f"{FIELD}.type",
                hint=f"known: {', '.join(known_types('teleoperator'))}",
            )
        config = build_device_config("teleoperator", type_name, device_params, field=FIELD)
        teleoperator = make_device("teleoperator", config, field=FIELD)
        keys, norms = _joint_keys(teleoperator, type_name, robot)
        require_calibration(teleoperator, kind="teleop", type_name=type_name, params=device_params, field=FIELD)
        return cls(robot, teleoperator, type_name=type_name, keys=keys, conversion=UnitConversion(robot, norms))

    @property
    def info(self) -> RSkillInfo:
        """Identity of the ``lerobot_teleop`` skill."""
        return self.INFO

    def _on_activate(self) -> None:
        try:
            self.teleoperator.connect(calibrate=False)
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
        """Disconnect the teleoperator, and any of its buses a failed connection left open."""
        if self.teleoperator.is_connected:
            self.teleoperator.disconnect()
        for found in motor_buses(self.teleoperator):
            if found.bus.is_connected:
                with contextlib.suppress(Exception):  # best effort after a failure already raised
                    found.bus.disconnect(disable_torque=False)

    def _step_impl(self, world_state: WorldState) -> Action:
        stamp = time.monotonic_ns()
        reading = self.teleoperator.get_action()
        values = np.fromiter((reading[key] for key in self.keys), dtype=np.float64, count=len(self.keys))
        return Action(
            control_mode=ControlMode.JOINT_POSITION,
            joint_names=self._names,
            targets=[self.conversion.to_radians(values).tolist()],
            stamp_ns=stamp,
            skill_id=SKILL_ID,
        )


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
