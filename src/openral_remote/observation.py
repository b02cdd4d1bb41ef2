"""A world state as wire fields and back: what a remote policy sees is what a local one would.

Fields: ``stamp_ns``, ``task``, ``joint.names`` / ``joint.positions`` / ``joint.velocities``,
``ee_pose``, ``image.<sensor>`` (the pixels, raw or JPEG) with ``image.<sensor>.meta``, and
``privileged.<name>``. A policy that says what it reads (``RSkillInfo.observation``: ``joint_state``,
``images`` or ``images.<sensor>``, ``privileged`` or ``privileged.<name>``, ``task``, ``ee_pose``)
is sent only that: a joint-space policy never costs the link a camera image.

A chunk request (:func:`request_fields`) is the current observation's fields plus what the chunk
executor knows by tick, so a served policy sees what a local one would: ``history.<i>.<field>``
for each earlier observation (oldest first, ``i`` from 0, the same fields as the current one),
``obs_tick``, ``inference_delay``, ``prefix`` (the targets sent while it infers) and ``seed`` (the
robot's episode seed). A server checks each against the policy's bounds from the header
(:mod:`openral_remote.admission`) before decoding.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from openral_core import FrameEncoding, JointState, Pose6D, PrivilegedState, SensorFrame, WorldState
from openral_remote.codec import WireFormatError
from openral_rskill.chunks import ChunkRequest

HISTORY = "history."
"""Prefix of an earlier observation's fields: ``history.<i>.<field>``, ``i`` from 0, oldest first."""
OBS_TICK = "obs_tick"
INFERENCE_DELAY = "inference_delay"
PREFIX = "prefix"
SEED = "seed"

_COMPRESSED = frozenset({FrameEncoding.JPEG, FrameEncoding.PNG})


class _Selection:
    """Which parts of the world state go on the wire."""

    def __init__(self, fields: Sequence[str]) -> None:
        wanted = set(fields)
        self.everything = not wanted
        self.joints = self.everything or "joint_state" in wanted
        self.task = self.everything or "task" in wanted
        self.ee_pose = self.everything or "ee_pose" in wanted
        self.all_images = self.everything or "images" in wanted
        self.images = {name.removeprefix("images.") for name in wanted if name.startswith("images.")}
        self.all_privileged = self.everything or "privileged" in wanted
        self.privileged = {name.removeprefix("privileged.") for name in wanted if name.startswith("privileged.")}

    def image(self, sensor_id: str) -> bool:
        return self.all_images or sensor_id in self.images

    def value(self, name: str) -> bool:
        return self.all_privileged or name in self.privileged


def world_fields(
    world: WorldState, observation: Sequence[str] = (), *, jpeg_quality: int | None = None
) -> tuple[dict[str, Any], dict[str, int]]:
    """The wire fields of ``world`` (only those ``observation`` names, all when empty), and the JPEG map.

    Returns:
        ``(fields, jpeg)``, as :func:`openral_remote.codec.encode` takes them.
    """
    selection = _Selection(observation)
    fields: dict[str, Any] = {"stamp_ns": world.stamp_ns}
    jpeg: dict[str, int] = {}
    if selection.task:
        fields["task"] = world.task
    joints = world.joint_state
    if selection.joints and joints is not None:
        fields["joint.names"] = list(joints.names)
        fields["joint.positions"] = np.asarray(joints.positions, dtype=np.float64)
        fields["joint.stamp_ns"] = joints.stamp_ns
        if joints.velocities is not None:
            fields["joint.velocities"] = np.asarray(joints.velocities, dtype=np.float64)
    if selection.ee_pose and world.ee_pose is not None:
        fields["ee_pose"] = world.ee_pose.model_dump()
    for sensor_id, frame in (world.image_frames or {}).items():
        if selection.image(sensor_id) and frame.data is not None:
            _put_frame(fields, jpeg, frame, jpeg_quality)
    if world.privileged is not None:
        for name, values in world.privileged.values.items():
            if selection.value(name):
                fields[f"privileged.{name}"] = np.asarray(values, dtype=np.float64)
    return fields, jpeg


def request_fields(
    request: ChunkRequest,
    observation: Sequence[str] = (),
    *,
    history: int,
    prefix_rows: int,
    seed: int | None = None,
    jpeg_quality: int | None = None,
) -> tuple[dict[str, Any], dict[str, int]]:
    """The wire fields of a chunk request, within a policy's bounds.

    Args:
        request: What the executor asks with.
        observation: What the policy reads (as :func:`world_fields`), of each observation.
        history: Earlier observations the policy reads at most: the latest of the request's are sent.
        prefix_rows: Prefix rows the policy takes at most: the first of the request's are sent.
        seed: The episode's seed, sent when the request carries none.
        jpeg_quality: As :func:`world_fields`, for every observation.

    Returns:
        ``(fields, jpeg)``, as :func:`openral_remote.codec.encode` takes them.
    """
    fields, jpeg = world_fields(request.world, observation, jpeg_quality=jpeg_quality)
    earlier = request.history[len(request.history) - history :] if history > 0 else ()
    for index, world in enumerate(earlier):
        past, past_jpeg = world_fields(world, observation, jpeg_quality=jpeg_quality)
        fields.update({f"{HISTORY}{index}.{name}": value for name, value in past.items()})
        jpeg.update({f"{HISTORY}{index}.{name}": quality for name, quality in past_jpeg.items()})
    fields[OBS_TICK] = int(request.obs_tick)
    fields[INFERENCE_DELAY] = int(request.inference_delay)
    prefix = np.asarray(request.prefix, dtype=np.float64)[:prefix_rows]
    if prefix.ndim == 2 and prefix.size:
        fields[PREFIX] = prefix
    seed = request.seed if request.seed is not None else seed
    if seed is not None:
        fields[SEED] = int(seed)
    return fields, jpeg


def request_from_fields(fields: Mapping[str, Any], *, action_dims: int) -> ChunkRequest:
    """The chunk request a message carries (a bare observation is a request without history or prefix).

    Raises:
        WireFormatError: A field of the wrong type, a gap in the history, or a prefix of another width.
    """
    current: dict[str, Any] = {}
    earlier: dict[int, dict[str, Any]] = {}
    for name, value in fields.items():
        if name.startswith(HISTORY):
            index, dot, rest = name.removeprefix(HISTORY).partition(".")
            if not (dot and index.isdecimal() and index == str(int(index))):
                raise WireFormatError(f"field {name!r}: not history.<index>.<field>")
            earlier.setdefault(int(index), {})[rest] = value
        else:
            current[name] = value
    if sorted(earlier) != list(range(len(earlier))):
        raise WireFormatError(f"history entries {sorted(earlier)[:8]} are not 0, 1, 2, ...")
    prefix = current.get(PREFIX)
    if prefix is None:
        prefix = np.zeros((0, action_dims))
    elif not isinstance(prefix, np.ndarray) or prefix.ndim != 2 or prefix.shape[1] != action_dims:
        raise WireFormatError(f"field {PREFIX!r}: not ({action_dims}-wide) rows")
    return ChunkRequest(
        world_from_fields(current),
        obs_tick=_int(current, OBS_TICK) or 0,
        history=tuple(world_from_fields(earlier[index]) for index in range(len(earlier))),
        prefix=np.asarray(prefix, dtype=np.float64),
        inference_delay=_int(current, INFERENCE_DELAY) or 0,
        seed=_int(current, SEED),
    )


def _int(fields: Mapping[str, Any], name: str) -> int | None:
    value = fields.get(name)
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool):
        raise WireFormatError(f"field {name!r}: not an integer")
    return value


def _put_frame(fields: dict[str, Any], jpeg: dict[str, int], frame: SensorFrame, quality: int | None) -> None:
    key = f"image.{frame.sensor_id}"
    encoding = frame.encoding
    if encoding in _COMPRESSED:
        assert frame.data is not None
        pixels = np.frombuffer(frame.data, dtype=np.uint8)
    elif quality is not None and encoding in (FrameEncoding.RGB8, FrameEncoding.BGR8):
        pixels = frame.as_rgb()  # JPEG takes RGB: a BGR camera's channels reordered by a view
        encoding = FrameEncoding.RGB8
        jpeg[key] = quality
    else:
        pixels = frame.as_array()
    fields[key] = pixels
    fields[f"{key}.meta"] = {
        "encoding": encoding.value,
        "width": frame.width,
        "height": frame.height,
        "stamp_ns": frame.stamp_ns,
        "seq": frame.seq,
        "frame_id": frame.frame_id,
    }


def world_from_fields(fields: Mapping[str, Any]) -> WorldState:
    """The world state a message carries.

    Raises:
        WireFormatError: A field of the wrong type, or an image whose description does not fit it.
    """
    try:
        return _world(fields)
    except (TypeError, ValueError, KeyError) as exc:
        raise WireFormatError(f"not an observation: {exc}") from None


def _world(fields: Mapping[str, Any]) -> WorldState:
    joint_state = None
    if "joint.positions" in fields:
        velocities = fields.get("joint.velocities")
        joint_state = JointState(
            names=list(fields["joint.names"]),
            positions=_array(fields["joint.positions"]).tolist(),
            velocities=None if velocities is None else _array(velocities).tolist(),
            stamp_ns=int(fields.get("joint.stamp_ns", 0)),
        )
    frames: dict[str, SensorFrame] = {}
    privileged: dict[str, list[float]] = {}
    for name, value in fields.items():
        if name.startswith("image.") and not name.endswith(".meta"):
            sensor_id = name.removeprefix("image.")
            meta = fields[f"{name}.meta"]
            if FrameEncoding(meta["encoding"]) in _COMPRESSED:
                _check_compressed_size(name, _array(value), (int(meta["width"]), int(meta["height"])))
            frames[sensor_id] = SensorFrame(
                sensor_id=sensor_id,
                stamp_ns=int(meta["stamp_ns"]),
                width=int(meta["width"]),
                height=int(meta["height"]),
                encoding=FrameEncoding(meta["encoding"]),
                seq=int(meta["seq"]),
                frame_id=meta.get("frame_id"),
                data=_array(value),
            )
        elif name.startswith("privileged."):
            privileged[name.removeprefix("privileged.")] = _array(value).tolist()
    pose = fields.get("ee_pose")
    return WorldState(
        stamp_ns=int(fields["stamp_ns"]),
        task=fields.get("task"),
        joint_state=joint_state,
        ee_pose=None if pose is None else Pose6D.model_validate(pose),
        image_frames=frames or None,
        privileged=PrivilegedState(values=privileged) if privileged else None,
    )


def _check_compressed_size(name: str, data: np.ndarray, announced: tuple[int, int]) -> None:
    """Refuse a JPEG or PNG whose own header says another size than its description (read lazily: no pixel decoded)."""
    from PIL import Image, UnidentifiedImageError  # noqa: PLC0415

    try:
        with Image.open(io.BytesIO(data.tobytes()), formats=["JPEG", "PNG"]) as image:
            size = image.size
    except (OSError, UnidentifiedImageError, Image.DecompressionBombError) as exc:
        raise WireFormatError(f"field {name!r}: not a JPEG or PNG ({exc})") from None
    if size != announced:
        raise WireFormatError(
            f"field {name!r}: an image of {size[0]}x{size[1]} described as {announced[0]}x{announced[1]}"
        )


def _array(value: Any) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        raise TypeError(f"expected an array, got {type(value).__name__}")
    return value
