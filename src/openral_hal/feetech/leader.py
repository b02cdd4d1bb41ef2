"""``SO10xLeaderArm``: the leader arm of an SO-100/SO-101 teleoperation pair, read on its own Feetech bus.

A leader is the same kinematic chain with the same servos, moved by the operator's hand: it is
opened like the follower (one port, its own calibration file), but its torque is switched off
and it is only ever read. ``emulate: true`` runs it on the servo-bus emulator; with a
``trajectory`` file the emulated leader replays a recorded motion, so teleoperated recording runs
end to end without hardware. The file is JSON: ``[{"t": seconds, "positions": {joint: rad}}, ...]``.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

from openral_core.actions import Action
from openral_core.config_files import read_config_file
from openral_core.errors import ROSConfigError
from openral_hal.feetech import protocol as p
from openral_hal.feetech.bus import FeetechBus
from openral_hal.feetech.emulator import ServoBusEmulator
from openral_hal.feetech.hal import SO10xFollowerHAL, SO10xFollowerParams
from openral_hal.feetech.protocol import Register


class SO10xLeaderParams(SO10xFollowerParams):
    """Parameters of a leader arm: the follower's bus settings, plus a trajectory for the emulated one.

    Attributes:
        trajectory: With ``emulate``: a recorded motion the emulated leader replays, looping.
    """

    torque_off_on_disconnect: bool = False
    trajectory: Path | None = None


class SO10xLeaderArm(SO10xFollowerHAL):
    """Reads the operator's leader arm (torque off) in the follower's joint names and radians."""

    adapter = "so10x_leader"
    params_model = SO10xLeaderParams
    field_prefix = "vla.params"

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
        trajectory = getattr(self.params, "trajectory", None)
        if trajectory is not None:
            emulator.play(self._trajectory_ticks(trajectory))
        return emulator

    def _trajectory_ticks(self, path: Path) -> list[tuple[float, dict[int, int]]]:
        field = f"{self.field_prefix}.trajectory"
        try:
            samples = json.loads(read_config_file(path, field=field))
            out = []
            for sample in samples:
                ticks = {}
                for joint, radians in sample["positions"].items():
                    cal = self.calibration.joints[joint]
                    ticks[cal.servo_id] = min(max(cal.to_ticks(float(radians)), 0), p.MAX_TICK)
                out.append((float(sample["t"]), ticks))
            if not out or any(b[0] <= a[0] for a, b in itertools.pairwise(out)):
                raise ValueError("the samples' times must increase")
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ROSConfigError(
                f"{path} is not a trajectory: {exc!r}",
                field=field,
                hint='JSON: [{"t": seconds, "positions": {joint: radians}}, ...] with increasing t',
            ) from exc
        return out
