"""From a ``WorldState`` to the arrays a LeRobot policy's preprocessor takes, checked against its features.

Every input feature of the checkpoint gets a source when the skill is built, or the build fails
naming the feature: nothing is ever filled with zeros.

* ``observation.state``: the measured joints, in the robot manifest's order on a robot (in the
  policy's ``joint_units``), or the simulator's state vector as it gives it (what openral records
  as ``observation.state`` in simulation).
* ``observation.environment_state``: the simulator's privileged ``environment_state``.
* ``observation.images.<camera>``: the frame of the sensor of that name (or the one ``cameras``
  maps it to), as RGB, resized to the feature's height and width, ``(3, H, W)`` floats in [0, 1].
* ``task``: the deployment's instruction, for policies that read language.

Arrays are float32 and unbatched, as LeRobot's preprocessor expects them.
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from PIL import Image

from openral_core import FrameEncoding, RobotManifest, ROSConfigError, SensorFrame, WorldState
from openral_hal.lerobot.units import UnitConversion
from openral_rskill.lerobot.checkpoint import ENVIRONMENT_STATE, IMAGE_PREFIX, STATE, Checkpoint, Feature

_FIELD = "params.path"


@dataclass(frozen=True)
class _Image:
    key: str
    sensor: str
    height: int
    width: int


class ObservationMap:
    """The policy's inputs from world states.

    Args:
        checkpoint: What the policy reads.
        robot: This robot's joints (their order is the state's on a robot).
        units: How the state and actions convert (radians: not at all).
        cameras: Policy camera name → sensor id, where they differ.

    Raises:
        ROSConfigError: A feature the deployment cannot supply, or one of a shape it cannot give.
    """

    def __init__(
        self,
        checkpoint: Checkpoint,
        *,
        robot: RobotManifest,
        units: UnitConversion,
        cameras: Mapping[str, str] | None = None,
    ) -> None:
        cameras = dict(cameras or {})
        unknown = sorted(set(cameras) - set(checkpoint.cameras))
        if unknown:
            raise ROSConfigError(
                f"the policy reads no camera {unknown}; it reads {checkpoint.cameras or 'none'}",
                field="params.cameras",
            )
        self.robot = robot
        self.units = units
        self.state: Feature | None = None
        self.environment_state: Feature | None = None
        self.images: list[_Image] = []
        for key, feature in checkpoint.inputs.items():
            if key == STATE:
                self.state = _vector(feature)
            elif key == ENVIRONMENT_STATE:
                self.environment_state = _vector(feature)
            elif key.startswith(IMAGE_PREFIX):
                name = key.removeprefix(IMAGE_PREFIX)
                if len(feature.shape) != 3 or feature.shape[0] != 3:
                    raise ROSConfigError(
                        f"feature {key} has shape {list(feature.shape)}; openral supplies (3, H, W) RGB images",
                        field=_FIELD,
                    )
                self.images.append(_Image(key, cameras.get(name, name), feature.shape[1], feature.shape[2]))
            else:
                raise ROSConfigError(
                    f"the policy reads {key} ({feature.kind}), which openral cannot supply "
                    f"(it supplies {STATE}, {ENVIRONMENT_STATE} and {IMAGE_PREFIX}<camera>)",
                    field=_FIELD,
                )
        if not units.identity:  # converted joint by joint: only a robot's joints can be
            self._check_state_size()

    def check_robot(self) -> None:
        """Refuse, on a robot, what only a simulator's world state gives.

        On a robot the state is the measured joints, one value each; a simulator's state vector
        (velocities, object poses) and its ``environment_state`` exist only there.

        Raises:
            ROSConfigError: A state of another size than the robot's joints, or an environment state.
        """
        self._check_state_size()
        if self.environment_state is not None:
            raise ROSConfigError(
                f"the policy reads {ENVIRONMENT_STATE}, which only a simulator gives",
                field=_FIELD,
                hint="run it in simulation, or train a policy on what the robot measures",
            )

    def _check_state_size(self) -> None:
        if self.state is not None and self.state.shape[0] != len(self.robot.joints):
            raise ROSConfigError(
                f"{STATE} has {self.state.shape[0]} values but robot '{self.robot.robot_id}' has "
                f"{len(self.robot.joints)} joints",
                field=_FIELD,
            )

    @property
    def reads(self) -> list[str]:
        """What of the world state the policy reads, in ``RSkillInfo.observation``'s words."""
        fields = []
        if self.state is not None:
            fields.append("joint_state")
        if self.environment_state is not None:
            fields.append("privileged.environment_state")
        fields += [f"images.{image.sensor}" for image in self.images]
        return [*fields, "task"]

    def arrays(self, world: WorldState) -> dict[str, np.ndarray]:
        """The policy's inputs for ``world`` (without ``task``).

        Raises:
            ValueError: The world state lacks a value the policy reads, or has one of another size.
        """
        out: dict[str, np.ndarray] = {}
        if self.state is not None:
            out[STATE] = _sized(self._state_vector(world), self.state)
        if self.environment_state is not None:
            values = None if world.privileged is None else world.privileged.get("environment_state")
            if values is None:
                raise ValueError(f"{ENVIRONMENT_STATE} needs the simulator's environment_state: it runs in simulation")
            out[ENVIRONMENT_STATE] = _sized(np.asarray(values, dtype=np.float64), self.environment_state)
        for image in self.images:
            frame = (world.image_frames or {}).get(image.sensor)
            if frame is None or frame.data is None:
                raise ValueError(f"{image.key} needs a frame of camera '{image.sensor}', and there is none")
            out[image.key] = _chw(_rgb(frame), image.height, image.width)
        return out

    def _state_vector(self, world: WorldState) -> np.ndarray:
        joints = world.joint_state
        if joints is None:
            raise ValueError(f"{STATE} needs the measured joints, and there are none")
        positions = np.asarray(joints.positions, dtype=np.float64)
        names = self.robot.joint_names
        if list(joints.names) != names and set(names) <= set(joints.names):
            index = {name: i for i, name in enumerate(joints.names)}
            positions = positions[[index[name] for name in names]]
        return self.units.to_policy(positions) if not self.units.identity else positions

    def blank(self) -> dict[str, np.ndarray]:
        """Inputs of the right shapes for a warm-up inference (the statistics' means are not needed)."""
        out: dict[str, np.ndarray] = {}
        for feature in (self.state, self.environment_state):
            if feature is not None:
                out[feature.key] = np.zeros(feature.shape, dtype=np.float32)
        for image in self.images:
            out[image.key] = np.full((3, image.height, image.width), 0.5, dtype=np.float32)
        return out


def _vector(feature: Feature) -> Feature:
    if len(feature.shape) != 1:
        raise ROSConfigError(
            f"feature {feature.key} has shape {list(feature.shape)}; a vector is expected", field=_FIELD
        )
    return feature


def _sized(values: np.ndarray, feature: Feature) -> np.ndarray:
    flat = np.asarray(values, dtype=np.float32).reshape(-1)
    if flat.shape != feature.shape:
        raise ValueError(f"{feature.key} has {flat.size} values here; the policy was trained on {feature.shape[0]}")
    return flat


def _rgb(frame: SensorFrame) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB of a frame: decoded from JPEG, else the frame's RGB view (no copy).

    Raises:
        ValueError: A frame with no 8-bit colour or grey to show (16-bit depth, PNG), naming the camera.
    """
    if frame.encoding == FrameEncoding.JPEG:
        data = frame.data if isinstance(frame.data, bytes | bytearray) else bytes(np.asarray(frame.data))
        with Image.open(io.BytesIO(data)) as picture:
            return np.asarray(picture.convert("RGB"))
    return frame.as_rgb()


def _chw(rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """``(3, height, width)`` float32 in [0, 1], resized bilinearly when the camera's size differs."""
    if rgb.shape[0] != height or rgb.shape[1] != width:
        resized = Image.fromarray(np.ascontiguousarray(rgb)).resize((width, height), Image.Resampling.BILINEAR)
        rgb = np.asarray(resized)
    return np.ascontiguousarray(rgb.transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0)


__all__ = ["ObservationMap"]
