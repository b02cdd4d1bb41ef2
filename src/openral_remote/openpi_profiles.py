"""openpi observation dicts to and from a :class:`~openral_core.WorldState`, per client profile.

openpi's protocol carries whatever dict the client sends; each checkpoint's input transforms decide
the keys. A profile is the dict of one of openpi's example clients, or openral's own:

* ``libero`` (``examples/libero``): ``observation/image`` and ``observation/wrist_image``,
  ``(S, S, 3)`` uint8, ``observation/state`` (8,) (end-effector position, axis-angle, two finger
  joints: openral's LIBERO state), ``prompt``. The example rotates robosuite's raw frames by 180°;
  those are upside down, so what it sends is the upright frame mirrored left to right (openral's
  ``camera_orientation: lerobot``). World frames are upright unless ``camera_orientation``
  says ``lerobot``.
* ``aloha`` (``examples/aloha_*``): ``state`` (14,), ``images: {cam_high, cam_low, cam_left_wrist,
  cam_right_wrist}`` each ``(3, S, S)`` uint8 channels first (``cam_high`` at least), ``prompt``.
* ``droid``: ``observation/exterior_image_1_left``, ``observation/wrist_image_left`` ``(S, S, 3)``,
  ``observation/joint_position`` (7,), ``observation/gripper_position`` (1,) (the state's 8th
  value), ``prompt``.
* ``openral``: openral's own fields, nothing resized: ``observation/state``,
  ``observation/joint_names``, ``observation/images/<sensor id>`` ``(H, W, 3)`` RGB,
  ``observation/privileged/<name>``, ``prompt``.

Images are resized as openpi's ``image_tools.resize_with_pad`` does (aspect kept, zero padding).
Cameras are the world's sensors named by ``cameras`` (slot → sensor id; each profile has defaults).

A server checks a request against the profile and the policy's inputs with :meth:`OpenpiProfile.check`
on the undecoded tree (:func:`openral_remote.msgpack_numpy.unpack_tree`), before any array is decoded.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Literal

import numpy as np

from openral_core import (
    FrameEncoding,
    JointState,
    PrivilegedState,
    ROSConfigError,
    ROSRuntimeError,
    SensorFrame,
    WorldState,
)
from openral_remote.codec import WireFormatError
from openral_remote.msgpack_numpy import ArrayHeader, array_header

ProfileName = Literal["openral", "libero", "aloha", "droid"]
PROFILES: Final[tuple[ProfileName, ...]] = ("openral", "libero", "aloha", "droid")
CameraOrientation = Literal["upright", "lerobot"]

PROMPT: Final = "prompt"
LIBERO_STATE_NAMES: Final = ("eef_x", "eef_y", "eef_z", "eef_rx", "eef_ry", "eef_rz", "finger_left", "finger_right")
"""openral's LIBERO state, the vector openpi's LIBERO example sends."""

OPENRAL_STATE: Final = "observation/state"
OPENRAL_JOINT_NAMES: Final = "observation/joint_names"
OPENRAL_IMAGES: Final = "observation/images/"
OPENRAL_PRIVILEGED: Final = "observation/privileged/"

MAX_IMAGE_SIDE: Final = 4096


@dataclass(frozen=True)
class _Layout:
    """Where a profile puts the state and the cameras."""

    state: tuple[tuple[str, int], ...]
    """The state, split in order over these keys: (key, values)."""
    slots: tuple[str, ...]
    required: tuple[str, ...]
    cameras: Mapping[str, str]
    """Default slot → sensor id."""
    images_key: str | None = None
    """The key of a map holding the slots (ALOHA's ``images``); ``None``: each slot is a key."""
    channels_first: bool = False
    mirror: bool = False
    state_names: tuple[str, ...] = field(default=())


_LAYOUTS: Final[dict[str, _Layout]] = {
    "libero": _Layout(
        state=(("observation/state", 8),),
        slots=("observation/image", "observation/wrist_image"),
        required=("observation/image", "observation/wrist_image"),
        cameras={"observation/image": "agentview", "observation/wrist_image": "robot0_eye_in_hand"},
        mirror=True,
        state_names=LIBERO_STATE_NAMES,
    ),
    "aloha": _Layout(
        state=(("state", 14),),
        slots=("cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist"),
        required=("cam_high",),
        cameras={"cam_high": "top"},
        images_key="images",
        channels_first=True,
    ),
    "droid": _Layout(
        state=(("observation/joint_position", 7), ("observation/gripper_position", 1)),
        slots=("observation/exterior_image_1_left", "observation/wrist_image_left"),
        required=("observation/exterior_image_1_left", "observation/wrist_image_left"),
        cameras={
            "observation/exterior_image_1_left": "exterior_image_1_left",
            "observation/wrist_image_left": "wrist_image_left",
        },
    ),
}


class OpenpiProfile:
    """One openpi client's observation dict, both ways.

    Args:
        name: The profile.
        cameras: Slot → the world's sensor id (replaces the profile's defaults; ``openral`` takes none).
        image_size: The side of the square images sent (``None``: as captured). A server checks it too.
        camera_orientation: ``libero``: whether the world's frames are upright or mirrored as LeRobot's
            LIBERO datasets store them (then they already are what openpi's example sends).
        state_names: The joint names a decoded state gets (the profile's own by default).

    Raises:
        ROSConfigError: A camera slot the profile does not have.
    """

    def __init__(
        self,
        name: ProfileName,
        *,
        cameras: Mapping[str, str] | None = None,
        image_size: int | None = 224,
        camera_orientation: CameraOrientation = "upright",
        state_names: Sequence[str] | None = None,
    ) -> None:
        if name not in PROFILES:
            raise ROSConfigError(f"unknown openpi profile {name!r} (one of {', '.join(PROFILES)})", field="profile")
        if image_size is not None and not 1 <= image_size <= MAX_IMAGE_SIDE:
            raise ROSConfigError(f"image_size {image_size} is not within 1..{MAX_IMAGE_SIDE}", field="image_size")
        self.name = name
        self.layout = _LAYOUTS.get(name)
        if self.layout is None:
            if cameras:
                raise ROSConfigError("the openral profile sends every camera by its sensor id", field="cameras")
            self.cameras: dict[str, str] = {}
        else:
            unknown = sorted(set(cameras or {}) - set(self.layout.slots))
            if unknown:
                raise ROSConfigError(
                    f"the {name} profile has no camera slot {unknown[0]!r} (slots: {', '.join(self.layout.slots)})",
                    field="cameras",
                )
            self.cameras = dict(self.layout.cameras if cameras is None else cameras)
            missing = [slot for slot in self.layout.required if slot not in self.cameras]
            if missing:
                raise ROSConfigError(f"the {name} profile needs a camera for {missing[0]!r}", field="cameras")
        self.image_size = image_size
        self.mirror = self.layout is not None and self.layout.mirror and camera_orientation == "upright"
        default_names = self.layout.state_names if self.layout is not None else ()
        self.state_names = tuple(state_names) if state_names is not None else default_names

    @property
    def state_dims(self) -> int | None:
        """Values of the state the profile sends (``None``: the robot's)."""
        return None if self.layout is None else sum(dims for _key, dims in self.layout.state)

    def world_fields(self) -> list[str]:
        """What it reads of a world state, as :attr:`RSkillInfo.observation` names it (openral: everything)."""
        if self.layout is None:
            return []
        return ["joint_state", *(f"images.{self.cameras[slot]}" for slot in self.cameras), "task"]

    # --- WorldState → obs ------------------------------------------------------------------------

    def observation(self, world: WorldState, *, reads: Sequence[str] = ()) -> dict[str, Any]:
        """The obs dict of ``world``.

        Args:
            world: The observation.
            reads: ``openral``: the fields the served policy reads (its meta's ``observation``; empty: all).

        Raises:
            ROSRuntimeError: The world lacks what the profile sends (a camera, the state, a state of
                another size).
        """
        if self.layout is None:
            return self._openral_observation(world, reads)
        layout = self.layout
        state = _state(world)
        dims = sum(n for _key, n in layout.state)
        if state.shape != (dims,):
            raise ROSRuntimeError(f"the {self.name} profile sends {dims} state values, the robot has {state.size}")
        obs: dict[str, Any] = {}
        start = 0
        for key, n in layout.state:
            obs[key] = state[start : start + n]
            start += n
        images = {slot: self._wire_image(_rgb(world, sensor)) for slot, sensor in self.cameras.items()}
        if layout.images_key is None:
            obs.update(images)
        else:
            obs[layout.images_key] = images
        if world.task is not None:
            obs[PROMPT] = world.task
        return obs

    def _wire_image(self, rgb: np.ndarray) -> np.ndarray:
        image = rgb[:, ::-1] if self.mirror else rgb
        if self.image_size is not None:
            image = resize_with_pad(image, self.image_size, self.image_size)
        if self.layout is not None and self.layout.channels_first:
            image = image.transpose(2, 0, 1)
        return np.ascontiguousarray(image)

    def _openral_observation(self, world: WorldState, reads: Sequence[str]) -> dict[str, Any]:
        wanted = set(reads)
        everything = not wanted
        obs: dict[str, Any] = {}
        if (everything or "joint_state" in wanted) and world.joint_state is not None:
            obs[OPENRAL_STATE] = _state(world)
            obs[OPENRAL_JOINT_NAMES] = list(world.joint_state.names)
        for sensor, frame in (world.image_frames or {}).items():
            if (everything or "images" in wanted or f"images.{sensor}" in wanted) and frame.data is not None:
                image = frame.as_rgb()
                if self.image_size is not None:
                    image = resize_with_pad(image, self.image_size, self.image_size)
                obs[OPENRAL_IMAGES + sensor] = np.ascontiguousarray(image)
        if world.privileged is not None:
            for name, values in world.privileged.values.items():
                if everything or "privileged" in wanted or f"privileged.{name}" in wanted:
                    obs[OPENRAL_PRIVILEGED + name] = np.asarray(values, dtype=np.float64)
        if (everything or "task" in wanted) and world.task is not None:
            obs[PROMPT] = world.task
        return obs

    # --- checks before decoding -------------------------------------------------------------------

    def check(self, tree: Any, *, reads: Sequence[str] = ()) -> None:
        """Refuse a request (the undecoded tree) that does not fit the profile or the policy's inputs.

        Args:
            tree: :func:`~openral_remote.msgpack_numpy.unpack_tree` of the request (openpi dialect).
            reads: The world-state fields the policy reads (``RSkillInfo.observation``; empty: the profile's).

        Raises:
            WireFormatError: Not a map, a missing or extra key (named), an array of another shape or
                dtype, or a field the policy reads that the request cannot carry.
        """
        if not isinstance(tree, dict) or not all(isinstance(key, str) for key in tree):
            raise WireFormatError(f"an openpi {self.name} observation is a map with text keys")
        provided = self._check_openral(tree) if self.layout is None else self._check_layout(tree, self.layout)
        for name in reads:
            if not _covered(name, provided):
                raise WireFormatError(f"the policy reads {name!r}, which this {self.name} request does not carry")

    def _check_layout(self, tree: dict[str, Any], layout: _Layout) -> set[str]:
        expected = {key for key, _n in layout.state} | {PROMPT}
        expected |= {layout.images_key} if layout.images_key is not None else set(self.cameras)
        _known_keys(tree, expected, required={key for key, _n in layout.state}, profile=self.name)
        for key, n in layout.state:
            _check_array(key, tree[key], "f", (n,))
        images = tree if layout.images_key is None else tree.get(layout.images_key)
        if not isinstance(images, dict):
            raise WireFormatError(f"missing key {layout.images_key!r} (a map of {', '.join(self.cameras)})")
        if layout.images_key is not None:
            _known_keys(images, set(self.cameras), required=set(), profile=self.name, parent=layout.images_key)
        for slot in layout.required:
            if slot not in images:
                raise WireFormatError(f"missing key {_path(layout.images_key, slot)!r} ({self.name} profile)")
        provided = {"joint_state"}
        for slot, sensor in self.cameras.items():
            if slot in images:
                side = self.image_size
                shape = (3, side, side) if layout.channels_first else (side, side, 3)
                _check_array(_path(layout.images_key, slot), images[slot], "u", shape, uint8=True)
                provided.add(f"images.{sensor}")
        _check_prompt(tree)
        if PROMPT in tree:
            provided.add("task")
        return provided

    def _check_openral(self, tree: dict[str, Any]) -> set[str]:
        provided: set[str] = set()
        for key, value in tree.items():
            if key == OPENRAL_STATE:
                names = tree.get(OPENRAL_JOINT_NAMES)
                size = len(names) if isinstance(names, list) else len(self.state_names) or None
                _check_array(key, value, "f", (size,))
                provided.add("joint_state")
            elif key == OPENRAL_JOINT_NAMES:
                if (
                    OPENRAL_STATE not in tree
                    or not isinstance(value, list)
                    or not all(isinstance(n, str) for n in value)
                ):
                    raise WireFormatError(f"key {key!r}: a list of joint names, sent with {OPENRAL_STATE!r}")
            elif key.startswith(OPENRAL_IMAGES) and len(key) > len(OPENRAL_IMAGES):
                side = self.image_size
                _check_array(key, value, "u", (side, side, 3), uint8=True)
                provided.add(f"images.{key.removeprefix(OPENRAL_IMAGES)}")
            elif key.startswith(OPENRAL_PRIVILEGED) and len(key) > len(OPENRAL_PRIVILEGED):
                _check_array(key, value, "f", (None,))
                provided.add(f"privileged.{key.removeprefix(OPENRAL_PRIVILEGED)}")
            elif key == PROMPT:
                _check_prompt(tree)
                provided.add("task")
            else:
                raise WireFormatError(f"unexpected key {_brief(key)} (openral profile)")
        if OPENRAL_STATE in tree and OPENRAL_JOINT_NAMES not in tree and not self.state_names:
            raise WireFormatError(f"missing key {OPENRAL_JOINT_NAMES!r} (the state's joint names)")
        return provided

    # --- obs → WorldState ------------------------------------------------------------------------

    def world(self, obs: Mapping[str, Any], *, stamp_ns: int, seq: int = 0) -> WorldState:
        """The world state a decoded obs dict (checked by :meth:`check`) stands for.

        Raises:
            WireFormatError: A value that does not fit (for a dict that skipped :meth:`check`).
        """
        try:
            if self.layout is None:
                return self._openral_world(obs, stamp_ns, seq)
            return self._layout_world(obs, self.layout, stamp_ns, seq)
        except (TypeError, ValueError, KeyError) as exc:
            raise WireFormatError(f"not an openpi {self.name} observation: {_brief(exc)}") from None

    def _layout_world(self, obs: Mapping[str, Any], layout: _Layout, stamp_ns: int, seq: int) -> WorldState:
        state = np.concatenate([np.asarray(obs[key], dtype=np.float64).reshape(-1) for key, _n in layout.state])
        images = obs if layout.images_key is None else obs[layout.images_key]
        frames: dict[str, SensorFrame] = {}
        for slot, sensor in self.cameras.items():
            if slot not in images:
                continue
            image = np.asarray(images[slot])
            if layout.channels_first:
                image = image.transpose(1, 2, 0)
            if self.mirror:
                image = image[:, ::-1]
            frames[sensor] = _frame(sensor, np.ascontiguousarray(image), stamp_ns, seq)
        names = list(self.state_names) if self.state_names else [f"state_{i}" for i in range(state.size)]
        return WorldState(
            stamp_ns=stamp_ns,
            joint_state=JointState(names=names, positions=state.tolist(), stamp_ns=stamp_ns),
            image_frames=frames or None,
            task=_prompt(obs),
        )

    def _openral_world(self, obs: Mapping[str, Any], stamp_ns: int, seq: int) -> WorldState:
        joint_state = None
        if OPENRAL_STATE in obs:
            state = np.asarray(obs[OPENRAL_STATE], dtype=np.float64).reshape(-1)
            names = obs.get(OPENRAL_JOINT_NAMES, list(self.state_names))
            joint_state = JointState(names=list(names), positions=state.tolist(), stamp_ns=stamp_ns)
        frames = {
            key.removeprefix(OPENRAL_IMAGES): _frame(key.removeprefix(OPENRAL_IMAGES), np.asarray(value), stamp_ns, seq)
            for key, value in obs.items()
            if key.startswith(OPENRAL_IMAGES)
        }
        privileged = {
            key.removeprefix(OPENRAL_PRIVILEGED): np.asarray(value, dtype=np.float64).reshape(-1).tolist()
            for key, value in obs.items()
            if key.startswith(OPENRAL_PRIVILEGED)
        }
        return WorldState(
            stamp_ns=stamp_ns,
            joint_state=joint_state,
            image_frames=frames or None,
            privileged=PrivilegedState(values=privileged) if privileged else None,
            task=_prompt(obs),
        )


def resize_with_pad(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """``(H, W, C)`` uint8 resized into ``(height, width, C)``, aspect kept, zero padding: openpi's ``image_tools``."""
    if image.shape[:2] == (height, width):
        return image
    from PIL import Image  # noqa: PLC0415

    source = Image.fromarray(np.ascontiguousarray(image))
    ratio = max(source.width / width, source.height / height)
    resized_height, resized_width = int(source.height / ratio), int(source.width / ratio)
    resized = source.resize((resized_width, resized_height), resample=Image.Resampling.BILINEAR)
    canvas = Image.new(resized.mode, (width, height), 0)
    canvas.paste(resized, (max(0, int((width - resized_width) / 2)), max(0, int((height - resized_height) / 2))))
    return np.asarray(canvas)


def _state(world: WorldState) -> np.ndarray:
    if world.joint_state is None:
        raise ROSRuntimeError("the world state has no joint state to send")
    return np.asarray(world.joint_state.positions, dtype=np.float64)


def _rgb(world: WorldState, sensor: str) -> np.ndarray:
    frame = (world.image_frames or {}).get(sensor)
    if frame is None or frame.data is None:
        raise ROSRuntimeError(f"the world state has no frame from camera {sensor!r}")
    try:
        return frame.as_rgb()
    except ValueError as exc:
        raise ROSRuntimeError(f"camera {sensor!r}: {exc}") from None


def _frame(sensor: str, image: np.ndarray, stamp_ns: int, seq: int) -> SensorFrame:
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"image {sensor!r} is not (H, W, 3) uint8")
    return SensorFrame(
        sensor_id=sensor,
        stamp_ns=stamp_ns,
        width=image.shape[1],
        height=image.shape[0],
        encoding=FrameEncoding.RGB8,
        seq=seq,
        data=image,
    )


def _prompt(obs: Mapping[str, Any]) -> str | None:
    prompt = obs.get(PROMPT)
    if prompt is not None and not isinstance(prompt, str):
        raise TypeError("prompt is not text")
    return prompt


def _covered(name: str, provided: set[str]) -> bool:
    """Whether a field the policy reads (``images`` or ``images.<id>``, ``privileged...``) is in the request."""
    if name in provided:
        return True
    if name in ("images", "privileged"):
        return any(field.startswith(f"{name}.") for field in provided)
    return False


def _known_keys(
    tree: dict[str, Any], expected: set[str], *, required: set[str], profile: str, parent: str | None = None
) -> None:
    extra = sorted(key for key in tree if key not in expected)
    if extra:
        raise WireFormatError(f"unexpected key {_brief(_path(parent, extra[0]))} ({profile} profile)")
    missing = sorted(required - set(tree))
    if missing:
        raise WireFormatError(f"missing key {_path(parent, missing[0])!r} ({profile} profile)")


def _check_array(key: str, node: Any, kinds: str, shape: tuple[int | None, ...], *, uint8: bool = False) -> None:
    """The encoded array's header against the expected dtype kind and shape (``None``: any size there)."""
    header: ArrayHeader | None = array_header(node)
    if header is None:
        raise WireFormatError(f"key {key!r}: not an array")
    if header.dtype.kind not in kinds or (uint8 and header.dtype.itemsize != 1):
        raise WireFormatError(f"key {key!r}: {header.dtype.str} where {'uint8' if uint8 else 'floats'} are expected")
    if len(header.shape) != len(shape) or any(
        e is not None and e != d for e, d in zip(shape, header.shape, strict=False)
    ):
        wanted = tuple("*" if e is None else e for e in shape)
        raise WireFormatError(f"key {key!r}: shape {header.shape} where {wanted} is expected")


def _texts(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(item, str) for item in value)


def _check_prompt(tree: dict[str, Any]) -> None:
    if PROMPT in tree and not isinstance(tree[PROMPT], str):
        raise WireFormatError(f"key {PROMPT!r}: not text")


def _path(parent: str | None, key: str) -> str:
    return key if parent is None else f"{parent}/{key}"


def _brief(value: Any) -> str:
    text = str(value) if isinstance(value, BaseException) else repr(value)
    return text if len(text) <= 80 else f"{text[:77]}..."
