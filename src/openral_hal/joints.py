"""Matching actions and configured positions to a robot's joints by name.

Every adapter needs the same three checks (known joint names, a supported control mode,
finite values) and the same default start pose; they live here once so that the twin, the
null HAL and the recording fake cannot disagree about the ``send_action`` contract.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping, Sequence

from openral_core.actions import Action, ControlMode
from openral_core.errors import ROSConfigError, ROSSafetyViolation
from openral_core.robot import RobotManifest

_CACHE_LIMIT = 64


class JointIndex:
    """Maps joint names onto positions in a robot's joint list.

    Name orders seen before are answered from a small cache, so a skill that always emits
    the same ``joint_names`` pays for one dictionary lookup per ``send_action``.

    Args:
        robot_id: Used in error messages.
        joint_names: The robot's joints, in the order the adapter stores them.
    """

    def __init__(self, robot_id: str, joint_names: Sequence[str]) -> None:
        self.robot_id = robot_id
        self.joint_names = list(joint_names)
        self._position = {name: i for i, name in enumerate(self.joint_names)}
        self._cache: dict[tuple[str, ...], tuple[int, ...]] = {}

    def indices(self, names: Sequence[str]) -> tuple[int, ...]:
        """Positions of ``names`` in the robot's joint list.

        Raises:
            ROSConfigError: A name is not one of the robot's joints.
        """
        key = tuple(names)
        found = self._cache.get(key)
        if found is not None:
            return found
        out: list[int] = []
        for name in key:
            index = self._position.get(name)
            if index is None:
                raise unknown_joint(self.robot_id, self.joint_names, name, field="action.joint_names")
            out.append(index)
        if len(self._cache) >= _CACHE_LIMIT:
            self._cache.clear()
        found = tuple(out)
        self._cache[key] = found
        return found

    def targets(self, action: Action, *, adapter: str) -> tuple[tuple[int, ...], list[float]]:
        """Joint positions and values of ``action.first``, checked against the ``send_action`` contract.

        Raises:
            ROSConfigError: Unknown joint name, or a control mode other than joint position.
            ROSSafetyViolation: A non-finite value.
        """
        if action.control_mode is not ControlMode.JOINT_POSITION:
            raise ROSConfigError(
                f"the {adapter} HAL of '{self.robot_id}' accepts {ControlMode.JOINT_POSITION.value} actions, "
                f"got {action.control_mode.value}",
                hint="use a skill that emits joint positions",
            )
        values = action.first
        for name, value in zip(action.joint_names, values, strict=True):
            if not math.isfinite(value):
                raise ROSSafetyViolation(
                    f"{adapter} HAL of '{self.robot_id}' refused a non-finite target {value} for joint '{name}'",
                    check_name="non_finite",
                )
        return self.indices(action.joint_names), values


def unknown_joint(robot_id: str, joint_names: Sequence[str], name: str, *, field: str) -> ROSConfigError:
    """The error for a joint name the robot lacks, listing its joints and the closest name."""
    close = difflib.get_close_matches(name, list(joint_names), n=1)
    return ROSConfigError(
        f"robot '{robot_id}' has no joint '{name}'; its joints: {', '.join(joint_names)}",
        field=field,
        hint=f"did you mean '{close[0]}'?" if close else None,
    )


def initial_positions(manifest: RobotManifest, given: Mapping[str, float]) -> list[float]:
    """Start positions in manifest order: ``given`` where named, else 0 clipped into the joint's limits.

    Zero is the calibrated middle of an SO-10x joint, so the default pose is the arm's neutral
    pose rather than a limit.

    Raises:
        ROSConfigError: ``given`` names an unknown joint or a position outside the joint's limits.
    """
    names = manifest.joint_names
    for name in given:
        if name not in names:
            raise unknown_joint(manifest.robot_id, names, name, field=f"hal.params.initial_positions.{name}")
    out: list[float] = []
    for spec in manifest.joints:
        if spec.name in given:
            value = float(given[spec.name])
            if not spec.lower <= value <= spec.upper:
                raise ROSConfigError(
                    f"{value} is outside joint '{spec.name}' limits [{spec.lower}, {spec.upper}]",
                    field=f"hal.params.initial_positions.{spec.name}",
                )
            out.append(value)
        else:
            out.append(min(max(0.0, spec.lower), spec.upper))
    return out
