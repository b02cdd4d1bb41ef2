"""``SO10xLeaderArm``: the leader arm of an SO-100/SO-101 teleoperation pair, read on its own Feetech bus.

A leader is the same kinematic chain with the same servos, moved by the operator's hand: it is
opened like the follower (one port, its own calibration file), but its torque is switched off
and it is only ever read. ``emulate: true`` runs it on the servo-bus emulator; with a
``trajectory`` file the emulated leader replays a recorded motion, so teleoperated recording runs
end to end without hardware. The file is JSON: ``[{"t": seconds, "positions": {joint: rad}}, ...]``.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, RootModel

from openral_core.actions import Action
from openral_core.config import validate_model
from openral_core.config_files import load_json_file
from openral_core.errors import ROSConfigError
from openral_core.robot import RobotManifest
from openral_hal.feetech import protocol as p
from openral_hal.feetech.bus import FeetechBus
from openral_hal.feetech.emulator import ServoBusEmulator
from openral_hal.feetech.hal import SO10xFollowerHAL, SO10xFollowerParams
from openral_hal.feetech.protocol import Register

_TRAJECTORY_HINT = 'JSON: [{"t": seconds, "positions": {joint: radians}}, ...] with increasing t'


class SO10xLeaderParams(SO10xFollowerParams):
    """Parameters of a leader arm: the follower's bus settings, plus a trajectory for the emulated one.

    Attributes:
        trajectory: With ``emulate``: a recorded motion the emulated leader replays, looping.
    """

    torque_off_on_disconnect: bool = False
    trajectory: Path | None = None


class _Sample(BaseModel):
    """One pose of a recorded leader motion."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    t: float = Field(ge=0)
    positions: dict[str, float]


class _Trajectory(RootModel[list[_Sample]]):
    """A recorded leader motion, as the trajectory file holds it."""


class SO10xLeaderArm(SO10xFollowerHAL):
    """Reads the operator's leader arm (torque off) in the follower's joint names and radians.

    Raises:
        ROSConfigError: As the follower's, or a trajectory file that cannot be replayed: it is
            read here, so ``openral validate`` refuses what connecting would.
    """

    adapter = "so10x_leader"
    params_model = SO10xLeaderParams
    field_prefix = "vla.params"

    def __init__(self, manifest: RobotManifest, params: Mapping[str, Any] | None = None) -> None:
        super().__init__(manifest, params)
        trajectory = getattr(self.params, "trajectory", None)
        self._replay = None if trajectory is None else self._trajectory_ticks(trajectory)

    def send_action(self, action: Action) -> None:
        """A leader is moved by hand and takes no command.

        Raises:
            ROSConfigError: Always.
        """
        raise ROSConfigError(f"the leader arm of '{self.robot_id}' is moved by hand; it takes no action")

    def estop(self) -> None:
        """Nothing to stop: the leader's torque is off."""

    def _prepare(self, bus: FeetechBus) -> None:
        bus.sync_write(Register.TORQUE_ENABLE, dict.fromkeys(self._ids, b"\x00"))

    def _make_emulator(self) -> ServoBusEmulator:
        emulator = super()._make_emulator()
        if self._replay is not None:
            emulator.play(self._replay)
        return emulator

    def _trajectory_ticks(self, path: Path) -> list[tuple[float, dict[int, int]]]:
        """The file's samples as servo ticks, checked: finite numbers, known joints, increasing times."""
        field = f"{self.field_prefix}.trajectory"
        data = load_json_file(path, field=field)
        samples = validate_model(_Trajectory, data, source=f"trajectory file {path}", field_prefix=field).root
        known = self.calibration.joints
        out = []
        for index, sample in enumerate(samples):
            unknown = sorted(set(sample.positions) - set(known))
            if unknown:
                raise ROSConfigError(
                    f"{path}: sample {index} moves joint(s) {unknown}, which the arm does not have "
                    f"({', '.join(known)})",
                    field=field,
                    hint=_TRAJECTORY_HINT,
                )
            ticks = {}
            for joint, radians in sample.positions.items():
                cal = known[joint]
                ticks[cal.servo_id] = min(max(cal.to_ticks(radians), 0), p.MAX_TICK)
            out.append((sample.t, ticks))
        if not out or any(b[0] <= a[0] for a, b in itertools.pairwise(out)):
            raise ROSConfigError(
                f"{path} is not a trajectory: {'it has no sample' if not out else 'the times do not increase'}",
                field=field,
                hint=_TRAJECTORY_HINT,
            )
        return out
