import numpy as np
import pytest

from openral_core import FrameEncoding, JointState, Pose6D, PrivilegedState, SensorFrame, WorldState
from openral_remote.codec import WireFormatError, decode, encode
from openral_remote.observation import world_fields, world_from_fields


def _world() -> WorldState:
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
    grey = rng.integers(0, 256, size=(48, 64), dtype=np.uint8)
    return WorldState(
        stamp_ns=123_456,
        task="pick the cube",
        joint_state=JointState(names=["a", "b"], positions=[0.25, -1.5], velocities=[0.0, 2.0], stamp_ns=99),
        ee_pose=Pose6D(x=0.1, y=0.2, z=0.3, yaw=1.0),
        image_frames={
            "front": SensorFrame(sensor_id="front", stamp_ns=5, width=64, height=48, encoding="bgr8", seq=7, data=bgr),
            "wrist": SensorFrame(sensor_id="wrist", stamp_ns=6, width=64, height=48, encoding="mono8", data=grey),
        },
        privileged=PrivilegedState(values={"target_pos": [0.1, 0.2, 0.03], "cube": [1.0]}),
    )


def _round_trip(world: WorldState, observation=(), jpeg_quality=None) -> WorldState:
    fields, jpeg = world_fields(world, observation, jpeg_quality=jpeg_quality)
    return world_from_fields(decode(encode(fields, jpeg=jpeg)))


def test_everything_a_local_policy_sees_arrives_exactly():
    world = _world()
    got = _round_trip(world)
    assert got.stamp_ns == world.stamp_ns
    assert got.task == world.task
    assert got.joint_state == world.joint_state
    assert got.ee_pose == world.ee_pose
    assert got.privileged == world.privileged
    assert got.image_frames is not None
    assert world.image_frames is not None
    for name, frame in world.image_frames.items():
        arrived = got.image_frames[name]
        assert (arrived.encoding, arrived.seq, arrived.stamp_ns) == (frame.encoding, frame.seq, frame.stamp_ns)
        np.testing.assert_array_equal(arrived.as_array(), frame.as_array())


def test_a_policy_that_says_what_it_reads_is_sent_only_that():
    fields, _jpeg = world_fields(_world(), ["joint_state", "privileged.target_pos"])
    assert not any(name.startswith("image.") for name in fields)
    assert "privileged.cube" not in fields
    got = world_from_fields(decode(encode(fields)))
    assert got.privileged == PrivilegedState(values={"target_pos": [0.1, 0.2, 0.03]})
    assert got.image_frames is None
    assert got.task is None


def test_one_named_camera_is_sent_and_the_others_are_not():
    fields, _jpeg = world_fields(_world(), ["images.wrist"])
    assert "image.wrist" in fields
    assert "image.front" not in fields
    assert "joint.positions" not in fields


def test_jpeg_sends_bgr_cameras_as_rgb_and_keeps_them_close():
    world = _world()
    smooth = np.zeros((48, 64, 3), dtype=np.uint8)
    smooth[..., 0] = 200  # blue in BGR
    smooth[..., 2] = 20
    frames = dict(world.image_frames or {})
    frames["front"] = SensorFrame(sensor_id="front", stamp_ns=1, width=64, height=48, encoding="bgr8", data=smooth)
    world = world.model_copy(update={"image_frames": frames})
    fields, jpeg = world_fields(world, jpeg_quality=90)
    assert set(jpeg) == {"image.front"}  # grey frames stay raw
    raw_size = len(encode(world_fields(world)[0]))
    message = encode(fields, jpeg=jpeg)
    assert len(message) < raw_size
    got = world_from_fields(decode(message))
    front = got.image_frames["front"]
    assert front.encoding is FrameEncoding.RGB8
    pixels = front.as_array().astype(int)
    assert abs(pixels[..., 2].mean() - 200) < 3  # blue is now the last channel
    assert abs(pixels[..., 0].mean() - 20) < 3


def test_a_message_that_is_not_an_observation_is_refused_by_name():
    with pytest.raises(WireFormatError, match="not an observation"):
        world_from_fields(decode(encode({"stamp_ns": 1, "joint.positions": "not an array", "joint.names": ["a"]})))
    with pytest.raises(WireFormatError, match="not an observation"):
        world_from_fields(decode(encode({"task": "no stamp"})))
