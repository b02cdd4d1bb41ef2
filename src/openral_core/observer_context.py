"""``ObserverContext``: the loop an observer watches, told to every observer plugin the same way.

A deployment and a simulated scene describe their loop differently (a robot manifest and its
sensors; an environment's spaces and rendered cameras). Observers are built from this one
description instead, so the same ``observers:`` entry means the same thing on either side.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from openral_core.environment import RobotEnvironment
from openral_core.robot import RobotManifest


class CameraSize(NamedTuple):
    """One camera of the loop and the size of its frames (0: not known before the first frame)."""

    id: str
    width: int
    height: int


@dataclass(frozen=True)
class ObserverContext:
    """What an observer plugin may know of the loop it watches; it opens nothing by itself.

    Attributes:
        robot_id: The robot (a scene's robot, or its environment when it simulates none).
        rate_hz: Ticks per second of the loop's own time (a simulated second in a scene).
        joint_names: The order of the measured state vector.
        action_names: The order of the commanded action vector.
        environment_state_names: The names of a simulator's flat object state (none on a robot).
        cameras: Every camera whose frames reach the world state.
        task: The instruction of the run.
        takeover: A person can take control mid-run (rows say whose action it was).
        free_running: Nothing outside the loop moves on while an observer catches up (a
            simulation): a recorder waits for its encoders instead of dropping frames.
        base_dir: The folder relative paths in the entry's parameters are resolved against.
        option: The command-line option the entry being built stands for (``--dataset-out``):
            its errors name that option. Set per entry by the builder from ``ObserverConfig.option``;
            ``None`` for a file's own entry.
    """

    robot_id: str
    rate_hz: float
    joint_names: tuple[str, ...] = ()
    action_names: tuple[str, ...] = ()
    environment_state_names: tuple[str, ...] = ()
    cameras: tuple[CameraSize, ...] = ()
    task: str = ""
    takeover: bool = False
    free_running: bool = False
    base_dir: Path | None = None
    option: str | None = None

    @classmethod
    def of_deployment(
        cls, env: RobotEnvironment, robot: RobotManifest, base_dir: Path | None = None
    ) -> ObserverContext:
        """The loop of a deployment: the robot's joints (state and action), one camera per sensor."""
        joints = tuple(robot.joint_names)
        return cls(
            robot_id=robot.robot_id,
            rate_hz=env.rate_hz,
            joint_names=joints,
            action_names=joints,
            cameras=tuple(CameraSize(s.sensor_id, s.width or 0, s.height or 0) for s in env.sensors),
            task=env.task.instruction or "",
            takeover=env.takeover is not None,
            base_dir=base_dir,
        )

    def camera_ids(self) -> list[str]:
        """The cameras' ids, in order."""
        return [camera.id for camera in self.cameras]
