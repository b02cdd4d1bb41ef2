"""openpi client profiles: a world state to each example client's obs dict, the checks a server makes, and back."""

import json

import numpy as np
import pytest

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
from openral_remote.msgpack_numpy import decode_tree, packb, unpack_tree
from openral_remote.openpi_profiles import LIBERO_STATE_NAMES, OpenpiProfile, resize_with_pad


def _image(height: int, width: int, salt: int = 0) -> np.ndarray:
    rng = np.random.default_rng(salt)
    return rng.integers(0, 256, (height, width, 3), dtype=np.uint8)


def _world(
    state: list[float],
    cameras: dict[str, np.ndarray],
    *,
    privileged: dict[str, list[float]] | None = None,
    names: list[str] | None = None,
    task: str | None = "pick up the cube",
) -> WorldState:
    frames = {
        sensor: SensorFrame(
            sensor_id=sensor,
            stamp_ns=5,
            width=image.shape[1],
            height=image.shape[0],
            encoding=FrameEncoding.RGB8,
            data=image,
        )
        for sensor, image in cameras.items()
    }
    return WorldState(
        stamp_ns=5,
        joint_state=JointState(names=names or [f"j{i}" for i in range(len(state))], positions=state),
        image_frames=frames or None,
        privileged=PrivilegedState(values=privileged) if privileged else None,
        task=task,
    )


def _over_the_wire(profile: OpenpiProfile, obs: dict[str, object], reads: tuple[str, ...] = ()) -> WorldState:
    """What a server makes of the obs: packed, checked undecoded, decoded, mapped back."""
    tree = unpack_tree(packb(obs))
    profile.check(tree, reads=reads)
    return profile.world(decode_tree(tree), stamp_ns=9)


LIBERO_STATE = [0.1, -0.2, 1.1, 3.1, 0.0, -0.08, 0.03, -0.03]


def test_libero_sends_what_openpis_example_sends() -> None:
    agent, wrist = _image(256, 256, 1), _image(256, 256, 2)
    obs = OpenpiProfile("libero").observation(_world(LIBERO_STATE, {"agentview": agent, "robot0_eye_in_hand": wrist}))
    assert sorted(obs) == ["observation/image", "observation/state", "observation/wrist_image", "prompt"]
    assert obs["observation/image"].shape == (224, 224, 3)
    assert obs["observation/image"].dtype == np.uint8
    # robosuite's raw frame is the upright one upside down; the example rotates it by 180°.
    raw = agent[::-1]
    np.testing.assert_array_equal(obs["observation/image"], resize_with_pad(raw[::-1, ::-1], 224, 224))
    np.testing.assert_array_equal(obs["observation/state"], LIBERO_STATE)
    assert obs["prompt"] == "pick up the cube"
    mirrored = OpenpiProfile("libero", camera_orientation="lerobot").observation(
        _world(LIBERO_STATE, {"agentview": raw[::-1, ::-1], "robot0_eye_in_hand": wrist})
    )
    np.testing.assert_array_equal(mirrored["observation/image"], obs["observation/image"])


def test_libero_round_trip_undoes_the_rotation() -> None:
    agent, wrist = _image(224, 224, 3), _image(224, 224, 4)
    profile = OpenpiProfile("libero")
    world = _over_the_wire(
        profile, profile.observation(_world(LIBERO_STATE, {"agentview": agent, "robot0_eye_in_hand": wrist}))
    )
    assert world.joint_state is not None
    assert world.joint_state.names == list(LIBERO_STATE_NAMES)
    np.testing.assert_allclose(world.joint_state.positions, LIBERO_STATE)
    assert world.image_frames is not None
    np.testing.assert_array_equal(world.image_frames["agentview"].as_rgb(), agent)
    np.testing.assert_array_equal(world.image_frames["robot0_eye_in_hand"].as_rgb(), wrist)
    assert world.task == "pick up the cube"


def test_aloha_sends_channels_first_and_round_trips() -> None:
    top = _image(480, 640, 5)
    profile = OpenpiProfile("aloha")
    obs = profile.observation(_world([0.01 * i for i in range(14)], {"top": top}))
    assert sorted(obs) == ["images", "prompt", "state"]
    assert list(obs["images"]) == ["cam_high"]
    assert obs["images"]["cam_high"].shape == (3, 224, 224)
    np.testing.assert_array_equal(obs["images"]["cam_high"], resize_with_pad(top, 224, 224).transpose(2, 0, 1))
    world = _over_the_wire(profile, obs)
    assert world.image_frames is not None
    np.testing.assert_array_equal(world.image_frames["top"].as_rgb(), resize_with_pad(top, 224, 224))
    assert world.joint_state is not None
    np.testing.assert_allclose(world.joint_state.positions, [0.01 * i for i in range(14)])


def test_droid_splits_the_state_and_round_trips() -> None:
    state = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.9]
    cams = {"exterior_image_1_left": _image(224, 224, 6), "wrist_image_left": _image(180, 320, 7)}
    profile = OpenpiProfile("droid")
    obs = profile.observation(_world(state, cams))
    np.testing.assert_array_equal(obs["observation/joint_position"], state[:7])
    np.testing.assert_array_equal(obs["observation/gripper_position"], [0.9])
    assert obs["observation/wrist_image_left"].shape == (224, 224, 3)
    world = _over_the_wire(profile, obs, reads=("joint_state", "images.wrist_image_left", "task"))
    assert world.joint_state is not None
    np.testing.assert_allclose(world.joint_state.positions, state)
    assert world.image_frames is not None
    np.testing.assert_array_equal(world.image_frames["exterior_image_1_left"].as_rgb(), cams["exterior_image_1_left"])


def test_openral_profile_sends_openrals_own_fields_and_round_trips() -> None:
    names = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
    front = _image(128, 128, 8)
    world = _world(
        [0.0, 0.1, 0.2, 0.3, 0.4, 0.5], {"front": front}, privileged={"cube_pos": [0.2, 0.0, 0.01]}, names=names
    )
    profile = OpenpiProfile("openral", image_size=None)
    obs = profile.observation(world)
    assert sorted(obs) == [
        "observation/images/front",
        "observation/joint_names",
        "observation/privileged/cube_pos",
        "observation/state",
        "prompt",
    ]
    only = profile.observation(world, reads=["joint_state", "privileged.cube_pos"])
    assert sorted(only) == ["observation/joint_names", "observation/privileged/cube_pos", "observation/state"]
    back = _over_the_wire(profile, obs, reads=("joint_state", "images.front", "privileged", "task"))
    assert back.joint_state is not None
    assert back.joint_state.names == names
    np.testing.assert_allclose(back.joint_state.positions, world.joint_state.positions)  # type: ignore[union-attr]
    assert back.privileged is not None
    assert back.privileged.values == {"cube_pos": [0.2, 0.0, 0.01]}
    assert back.image_frames is not None
    np.testing.assert_array_equal(back.image_frames["front"].as_rgb(), front)
    assert back.task == "pick up the cube"


def _libero_obs() -> dict[str, object]:
    return OpenpiProfile("libero").observation(
        _world(LIBERO_STATE, {"agentview": _image(224, 224), "robot0_eye_in_hand": _image(224, 224)})
    )


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda o: o.pop("observation/wrist_image"), "missing key 'observation/wrist_image'"),
        (lambda o: o.pop("observation/state"), "missing key 'observation/state'"),
        (lambda o: o.update({"observation/extra": 1}), "unexpected key 'observation/extra'"),
        (lambda o: o.update({"observation/state": np.zeros(7)}), r"shape \(7,\) where \(8,\)"),
        (lambda o: o.update({"observation/image": np.zeros((224, 224, 3), np.float32)}), "uint8"),
        (lambda o: o.update({"observation/image": np.zeros((256, 256, 3), np.uint8)}), "shape"),
        (lambda o: o.update({"observation/state": [0.0] * 8}), "not an array"),
        (lambda o: o.update({"observation/state": np.zeros(8, np.int64)}), "floats"),
        (lambda o: o.update({"prompt": 3}), "not text"),
    ],
)
def test_a_request_that_does_not_fit_the_profile_is_refused_undecoded(change, reason) -> None:  # type: ignore[no-untyped-def]
    obs = _libero_obs()
    change(obs)
    with pytest.raises(WireFormatError, match=reason):
        OpenpiProfile("libero").check(unpack_tree(packb(obs)))


def test_a_request_must_carry_what_the_policy_reads() -> None:
    profile = OpenpiProfile("libero")
    tree = unpack_tree(packb(_libero_obs()))
    profile.check(tree, reads=("joint_state", "images.agentview", "images", "task"))
    with pytest.raises(WireFormatError, match=r"'privileged\.cube_pos'"):
        profile.check(tree, reads=("privileged.cube_pos",))
    without_prompt = _libero_obs()
    del without_prompt["prompt"]
    with pytest.raises(WireFormatError, match="'task'"):
        profile.check(unpack_tree(packb(without_prompt)), reads=("task",))
    with pytest.raises(WireFormatError, match="text keys"):
        profile.check(unpack_tree(packb([1, 2])))


def test_aloha_and_openral_checks_name_the_bad_key() -> None:
    aloha = OpenpiProfile("aloha")
    obs = aloha.observation(_world([0.0] * 14, {"top": _image(224, 224)}))
    obs["images"]["cam_low"] = obs["images"]["cam_high"]  # type: ignore[index]
    with pytest.raises(WireFormatError, match="unexpected key 'images/cam_low'"):
        aloha.check(unpack_tree(packb(obs)))
    obs["images"] = {}
    with pytest.raises(WireFormatError, match="missing key 'images/cam_high'"):
        aloha.check(unpack_tree(packb(obs)))
    openral = OpenpiProfile("openral", image_size=None)
    with pytest.raises(WireFormatError, match="unexpected key 'state'"):
        openral.check(unpack_tree(packb({"state": np.zeros(3)})))
    with pytest.raises(WireFormatError, match="joint names"):
        openral.check(unpack_tree(packb({"observation/state": np.zeros(3)})))
    with pytest.raises(WireFormatError, match=r"shape \(3,\) where \(2,\)"):
        openral.check(unpack_tree(packb({"observation/state": np.zeros(3), "observation/joint_names": ["a", "b"]})))


def test_profile_configuration_errors_name_the_field() -> None:
    with pytest.raises(ROSConfigError, match="no camera slot 'cam_side'"):
        OpenpiProfile("aloha", cameras={"cam_side": "x"})
    with pytest.raises(ROSConfigError, match="needs a camera for 'cam_high'"):
        OpenpiProfile("aloha", cameras={"cam_low": "x"})
    with pytest.raises(ROSConfigError, match="unknown openpi profile"):
        OpenpiProfile("gr00t")  # type: ignore[arg-type]
    with pytest.raises(ROSConfigError, match="image_size"):
        OpenpiProfile("libero", image_size=0)
    assert OpenpiProfile("libero").world_fields() == [
        "joint_state",
        "images.agentview",
        "images.robot0_eye_in_hand",
        "task",
    ]


def test_a_world_without_what_the_profile_sends_is_an_error() -> None:
    with pytest.raises(ROSRuntimeError, match="camera 'robot0_eye_in_hand'"):
        OpenpiProfile("libero").observation(_world(LIBERO_STATE, {"agentview": _image(8, 8)}))
    with pytest.raises(ROSRuntimeError, match="8 state values, the robot has 6"):
        OpenpiProfile("libero").observation(_world([0.0] * 6, {}))


_RESIZE = """
import sys, json, numpy as np
from openpi_client import image_tools
rng = np.random.default_rng(0)
out = {}
for h, w in [(480, 640), (256, 256), (100, 333), (224, 224)]:
    img = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    out[f"{h}x{w}"] = image_tools.resize_with_pad(img, 224, 224).astype(int).sum(axis=(0, 1)).tolist()
print(json.dumps(out))
"""


@pytest.mark.slow
def test_resize_with_pad_matches_openpi_client(peer_venv) -> None:  # type: ignore[no-untyped-def]
    theirs = json.loads(peer_venv("openpi-client").run(_RESIZE).stdout)
    rng = np.random.default_rng(0)
    for h, w in [(480, 640), (256, 256), (100, 333), (224, 224)]:
        image = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        assert resize_with_pad(image, 224, 224).astype(int).sum(axis=(0, 1)).tolist() == theirs[f"{h}x{w}"]
