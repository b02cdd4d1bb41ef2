"""vla-eval's observations as openral world states: which benchmark names are which cameras and joints.

A vla-eval observation is a map: ``images`` (name → ``(H, W, C)`` uint8, PNG on the wire),
``states`` (the robot's state vector), other numeric arrays (``controller_states``...) and
``task_description``. A :class:`VlaEvalProfile` says how a benchmark's names map onto a
:class:`~openral_core.WorldState` (``images[name]`` → the camera of the profile's sensor for
``name``, ``states`` → the joint state named by the profile, other arrays → privileged values,
``task_description`` → task) and what the server tells the harness in ``hello`` (the observation
parameters to ask for, the action and observation specs).

:class:`ObservationReader` does the mapping in two steps, so a server spends nothing on pixels it
will not use: :meth:`~ObservationReader.world` reads everything but the pixels (small, checked), and
:meth:`~ObservationReader.frames` decodes only the cameras the policy reads, each image's size
checked from its header first (:meth:`~ObservationReader.check_images`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np

from openral_core import FrameEncoding, JointState, PrivilegedState, SensorFrame, WorldState
from openral_remote import msgpack_numpy
from openral_remote.admission import ImagesRead, Refused
from openral_remote.codec import WireFormatError

MAX_TEXT: Final = 4096
"""Characters of a task description (or a version string) kept."""
MAX_VALUES: Final = 4096
"""Elements of a state or privileged array taken."""
_ENCODINGS: Final = {1: FrameEncoding.MONO8, 3: FrameEncoding.RGB8, 4: FrameEncoding.RGBA8}


def _dim(name: str, dims: int, fmt: str, value_range: tuple[float, float] | None = None) -> dict[str, Any]:
    """A vla-eval ``DimSpec`` as it travels."""
    spec: dict[str, Any] = {"name": name, "dims": dims, "format": fmt}
    if value_range is not None:
        spec["range"] = list(value_range)
    return spec


@dataclass(frozen=True)
class VlaEvalProfile:
    """How a benchmark's observations map onto an openral world state, and what the harness is told.

    Attributes:
        cameras: vla-eval image name → openral camera (sensor) name; names not listed are kept.
        mirror: Mirror every frame left to right (LIBERO frames as LeRobot's datasets store them).
        state_names: Names of the ``states`` vector (``state_<i>`` when empty or of another length).
        observation_params: Benchmark parameters asked for in ``hello``: ``param: reader``, sent
            ``True`` when the policy reads ``reader`` (a world-state field, or ``images.<camera>``).
        action_spec / observation_spec: vla-eval ``DimSpec`` dicts (the harness checks them
            against the benchmark's and warns on a mismatch).
    """

    cameras: Mapping[str, str] = field(default_factory=dict)
    mirror: bool = False
    state_names: tuple[str, ...] = ()
    observation_params: Mapping[str, str] = field(default_factory=dict)
    action_spec: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    observation_spec: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    def sensor(self, image_name: str) -> str:
        return self.cameras.get(image_name, image_name)


_LIBERO = VlaEvalProfile(
    cameras={"wrist": "robot0_eye_in_hand"},
    state_names=("eef_x", "eef_y", "eef_z", "eef_rx", "eef_ry", "eef_rz", "finger_left", "finger_right"),
    observation_params={"send_state": "joint_state", "send_wrist_image": "images.robot0_eye_in_hand"},
    action_spec={
        "position": _dim("position", 3, "delta_xyz", (-1, 1)),
        "rotation": _dim("rotation", 3, "axis_angle", (-3.15, 3.15)),
        "gripper": _dim("gripper", 1, "binary_close_positive", (-1, 1)),
    },
    observation_spec={
        "agentview": _dim("image", 0, "rgb_hwc_uint8"),
        "language": _dim("language", 0, "language"),
    },
)

PROFILES: Final[dict[str, VlaEvalProfile]] = {
    "plain": VlaEvalProfile(),
    "libero": _LIBERO,
    "libero_lerobot": dataclasses.replace(_LIBERO, mirror=True),
}
"""``plain``: names as the benchmark sends them. ``libero``: LIBERO and its variants (LIBERO-Pro,
-Plus, -Mem) for openral's ``libero`` scenes (upright frames, the wrist camera named
``robot0_eye_in_hand``, LeRobot's 8-d state). ``libero_lerobot``: the same, frames mirrored as in
LeRobot's LIBERO datasets (``camera_orientation: lerobot``)."""


class ObservationReader:
    """Reads a vla-eval observation (its msgpack tree, arrays still encoded) for a policy.

    Args:
        profile: How the benchmark's names map onto openral's.
        images: The cameras the policy reads (others are never decoded).
        max_image_pixels: The largest image taken (width × height).
        limits: The codec's bounds.
    """

    def __init__(
        self, profile: VlaEvalProfile, *, images: ImagesRead, max_image_pixels: int, limits: msgpack_numpy.Limits
    ) -> None:
        self.profile = profile
        self._images = images
        self._max_image_pixels = max_image_pixels
        self._codec_limits = limits

    def check_images(self, payload: Mapping[str, Any]) -> None:
        """Every image the policy reads within the pixel limit, from its header (nothing decoded).

        Raises:
            WireFormatError: A malformed image, or one over the limit.
        """
        images = payload.get("images", {})
        if not isinstance(images, dict):
            raise WireFormatError("images is not a map")
        for name, node in images.items():
            if not self._images.reads(self.profile.sensor(name)):
                continue
            header = msgpack_numpy.array_header(node, dialect="vla_eval", limits=self._codec_limits)
            if header is None or len(header.shape) != 3 or header.dtype != np.uint8:
                raise WireFormatError(f"image {name[:40]!r} is not an (H, W, C) uint8 image")
            height, width = header.shape[:2]
            if height * width > self._max_image_pixels:
                raise Refused(f"image {name[:40]!r} of {width}x{height} is over {self._max_image_pixels} pixels")

    def world(self, payload: Mapping[str, Any], *, stamp_ns: int) -> WorldState:
        """The observation as a world state, its cameras not decoded yet (:meth:`frames`).

        Raises:
            WireFormatError: A malformed field.
        """
        state: JointState | None = None
        privileged: dict[str, list[float]] = {}
        for key, node in payload.items():
            if key in ("images", "task_description") or not isinstance(node, dict):
                continue
            header = msgpack_numpy.array_header(node, dialect="vla_eval", limits=self._codec_limits)
            if header is None or header.image_format is not None:
                continue
            if math.prod(header.shape) > MAX_VALUES:
                raise WireFormatError(f"{key[:40]!r} holds more than {MAX_VALUES} values")
            values = msgpack_numpy.decode_tree(node, dialect="vla_eval", limits=self._codec_limits)
            flat = np.asarray(values, dtype=np.float64).ravel()
            if key == "states":
                names = self.profile.state_names
                if len(names) != len(flat):
                    names = tuple(f"state_{i}" for i in range(len(flat)))
                state = JointState(names=list(names), positions=flat.tolist(), stamp_ns=stamp_ns)
            else:
                privileged[str(key)[:MAX_TEXT]] = flat.tolist()
        task = payload.get("task_description")
        return WorldState(
            stamp_ns=stamp_ns,
            joint_state=state,
            privileged=PrivilegedState(values=privileged) if privileged else None,
            task=task[:MAX_TEXT] if isinstance(task, str) else None,
        )

    def frames(self, payload: Mapping[str, Any], stamp_ns: int) -> dict[str, SensorFrame] | None:
        """The frames of the cameras the policy reads, decoded (mirrored where the profile says).

        Raises:
            WireFormatError: An image that does not decode to what its header announced.
        """
        images = payload.get("images")
        if not isinstance(images, dict):
            return None
        frames: dict[str, SensorFrame] = {}
        for name, node in images.items():
            sensor = self.profile.sensor(str(name))
            if not self._images.reads(sensor):
                continue
            pixels = msgpack_numpy.decode_tree(node, dialect="vla_eval", limits=self._codec_limits)
            if not isinstance(pixels, np.ndarray) or pixels.ndim != 3 or pixels.dtype != np.uint8:
                raise WireFormatError(f"image {str(name)[:40]!r} is not an (H, W, C) uint8 image")
            if self.profile.mirror:
                pixels = pixels[:, ::-1]
            pixels = np.ascontiguousarray(pixels)
            channels = pixels.shape[2]
            height, width = pixels.shape[:2]
            frames[sensor] = SensorFrame(
                sensor_id=sensor,
                stamp_ns=stamp_ns,
                width=width,
                height=height,
                encoding=_ENCODINGS[channels],
                data=pixels if channels != 1 else np.ascontiguousarray(pixels[:, :, 0]),
            )
        return frames or None


__all__ = ["MAX_TEXT", "MAX_VALUES", "PROFILES", "ObservationReader", "VlaEvalProfile"]
