"""Calibration of an SO-10x arm: where each servo's ticks put its joint, as a JSON or YAML file.

Per joint: ``homing_ticks`` is the servo reading at the joint's zero (the calibrated middle of
its range, matching the manifest and the MuJoCo model), ``range_min``/``range_max`` the ticks the
joint may be driven between (recorded by ``openral calibrate``), and ``direction`` ``+1`` or
``-1`` when the servo turns against the model's positive sense. Conversion::

    radians = direction * (ticks - homing_ticks) * 2π / 4096

Every joint, the jaw included, is in radians like the manifest; no 0..1 gripper scale.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Literal, Self

import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from openral_core.config import validate_model
from openral_core.config_files import load_config_file
from openral_core.errors import ROSConfigError
from openral_core.robot import RobotManifest
from openral_hal.feetech.protocol import MAX_TICK, RAD_PER_TICK, TICKS_PER_REV

_MIDDLE = TICKS_PER_REV // 2


class JointCalibration(BaseModel):
    """One joint's servo calibration, in ticks."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    servo_id: int = Field(ge=0, le=253)
    homing_ticks: int = Field(default=_MIDDLE, ge=0, le=MAX_TICK)
    range_min: int = Field(default=0, ge=0, le=MAX_TICK)
    range_max: int = Field(default=MAX_TICK, ge=0, le=MAX_TICK)
    direction: Literal[1, -1] = 1

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if self.range_min >= self.range_max:
            raise ValueError(f"range_min ({self.range_min}) must be below range_max ({self.range_max})")
        return self

    def to_radians(self, ticks: float) -> float:
        """Joint angle of a servo reading."""
        return self.direction * (ticks - self.homing_ticks) * RAD_PER_TICK

    def to_ticks(self, radians: float) -> int:
        """Servo goal for a joint angle, clipped into ``[range_min, range_max]``."""
        ticks = round(self.homing_ticks + self.direction * radians / RAD_PER_TICK)
        return min(max(ticks, self.range_min), self.range_max)


class ArmCalibration(BaseModel):
    """A calibration file: one entry per joint name."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    robot_id: str
    joints: dict[str, JointCalibration]

    @classmethod
    def from_manifest(cls, manifest: RobotManifest) -> ArmCalibration:
        """A nominal calibration: zero at tick 2048, range from the manifest's joint limits.

        Right for the emulator; a real arm needs ``openral calibrate``.

        Raises:
            ROSConfigError: A joint has no ``servo_id`` in the manifest.
        """
        joints = {}
        for spec in manifest.joints:
            if spec.servo_id is None:
                raise ROSConfigError(
                    f"joint '{spec.name}' of robot '{manifest.robot_id}' has no servo_id",
                    field=f"joints.{spec.name}.servo_id",
                )
            low = max(0, math.floor(_MIDDLE + spec.lower / RAD_PER_TICK))
            high = min(MAX_TICK, math.ceil(_MIDDLE + spec.upper / RAD_PER_TICK))
            joints[spec.name] = JointCalibration(servo_id=spec.servo_id, range_min=low, range_max=high)
        return cls(robot_id=manifest.robot_id, joints=joints)

    def check(self, manifest: RobotManifest) -> None:
        """Check that this file covers exactly the manifest's joints with their servo ids.

        Raises:
            ROSConfigError: A joint is missing or extra, or a servo id disagrees.
        """
        names = set(manifest.joint_names)
        if set(self.joints) != names:
            raise ROSConfigError(
                f"calibration for '{self.robot_id}' covers joints {sorted(self.joints)}, "
                f"robot '{manifest.robot_id}' has {sorted(names)}",
                field="hal.params.calibration",
                hint="re-run openral calibrate for this robot",
            )
        for spec in manifest.joints:
            if spec.servo_id is not None and self.joints[spec.name].servo_id != spec.servo_id:
                raise ROSConfigError(
                    f"calibration gives joint '{spec.name}' servo id {self.joints[spec.name].servo_id}, "
                    f"the manifest says {spec.servo_id}",
                    field="hal.params.calibration",
                )


def load_calibration(path: Path, *, field: str = "hal.params.calibration") -> ArmCalibration:
    """Read a calibration file (``.json``, or YAML for any other suffix); ``~`` is expanded.

    Args:
        field: Where the deployment names the file, for errors.

    Raises:
        ROSConfigError: The file is missing, unreadable, not a regular file, or invalid.
    """
    data = load_config_file(
        path, field=field, missing_hint="create it with: openral calibrate --robot <id> --port <port> --output <file>"
    )
    return validate_model(ArmCalibration, data, source=f"calibration file {path}", field_prefix=field)


def save_calibration(calibration: ArmCalibration, path: Path) -> None:
    """Write a calibration file (``.json``, or YAML for any other suffix), creating its folder."""
    data = calibration.model_dump(mode="json")
    text = json.dumps(data, indent=2) + "\n" if path.suffix == ".json" else yaml.safe_dump(data, sort_keys=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
