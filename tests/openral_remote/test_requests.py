"""A chunk request on the wire: history, prefix, tick and seed arrive as asked, within the policy's bounds."""

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from openral_core import FrameEncoding, JointState, SensorFrame, WorldState
from openral_remote.admission import ImagesRead, Refused, RequestBounds, ServeLimits, admit
from openral_remote.codec import decode, encode
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.observation import request_fields, request_from_fields
from openral_remote.server import PolicyServer
from openral_remote.session import PeerError, open_session, request
from openral_remote.testing import ChunkSkill, chunk_meta
from openral_rskill.chunks import ChunkRequest

pytestmark = pytest.mark.timeout(120)

NAMES = ["a0", "a1"]
BOUNDS = RequestBounds(history=2, prefix_rows=4, action_dims=2)


def _world(q: float, *, stamp: int = 1, camera: bool = False) -> WorldState:
    frames = None
    if camera:
        pixels = np.full((6, 8, 3), int(q * 10) % 256, dtype=np.uint8)
        frames = {
            "front": SensorFrame(
                sensor_id="front", stamp_ns=stamp, width=8, height=6, encoding=FrameEncoding.RGB8, data=pixels
            )
        }
    return WorldState(
        stamp_ns=stamp, joint_state=JointState(names=NAMES, positions=[q, -q]), image_frames=frames, task="t"
    )


def _request(history: int = 3, prefix_rows: int = 6, **kwargs: Any) -> ChunkRequest:
    return ChunkRequest(
        _world(9.0, stamp=9, camera=True),
        obs_tick=41,
        history=tuple(_world(float(i), stamp=i, camera=True) for i in range(history)),
        prefix=np.arange(prefix_rows * 2, dtype=np.float64).reshape(prefix_rows, 2),
        inference_delay=3,
        **kwargs,
    )


def _sent(asked: ChunkRequest, seed: int | None = None, bounds: RequestBounds = BOUNDS) -> bytes:
    fields, jpeg = request_fields(asked, history=bounds.history, prefix_rows=bounds.prefix_rows, seed=seed)
    return encode(fields, jpeg=jpeg)


def test_a_request_arrives_with_its_latest_history_its_prefix_tick_and_seed():
    asked = _request()
    message = _sent(asked, seed=7)
    admit(message, limits=ServeLimits(), images=ImagesRead.of([]), bounds=BOUNDS)
    got = request_from_fields(decode(message), action_dims=2)
    assert [w.stamp_ns for w in got.history] == [1, 2]  # the two latest of three, oldest first
    for arrived, sent in zip(got.history, asked.history[1:], strict=True):
        assert arrived.joint_state == sent.joint_state
        np.testing.assert_array_equal(arrived.image_frames["front"].as_array(), sent.image_frames["front"].as_array())
    assert got.world.joint_state == asked.world.joint_state
    np.testing.assert_array_equal(got.prefix, asked.prefix[:4])  # no more rows than the policy's chunk
    assert (got.obs_tick, got.inference_delay, got.seed) == (41, 3, 7)
    assert [w.stamp_ns for w in got.observations(3)] == [1, 2, 9]


def test_a_bare_observation_is_a_request_without_history_prefix_or_seed():
    fields, _jpeg = request_fields(ChunkRequest(_world(0.5)), history=0, prefix_rows=4)
    got = request_from_fields(decode(encode(fields)), action_dims=2)
    assert (got.history, got.prefix.shape, got.seed, got.obs_tick) == ((), (0, 2), None, 0)
    assert request_from_fields(decode(encode({"stamp_ns": 1})), action_dims=2).history == ()


def test_the_requests_own_seed_goes_before_the_episodes():
    fields, _jpeg = request_fields(_request(seed=3), history=2, prefix_rows=4, seed=7)
    assert fields["seed"] == 3


def _fields(**changes: Any) -> dict[str, Any]:
    fields, _jpeg = request_fields(_request(history=2, prefix_rows=2), history=2, prefix_rows=4, seed=1)
    fields.update(changes)
    return {name: value for name, value in fields.items() if value is not None}


def _huge_history_frame() -> dict[str, Any]:
    meta = {"encoding": "rgb8", "width": 6000, "height": 6000, "stamp_ns": 1, "seq": 0, "frame_id": None}
    return {"history.0.image.front": np.zeros((1, 1, 3), np.uint8), "history.0.image.front.meta": meta}


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"history.2.stamp_ns": 1}, "reads 2 earlier observations"),
        ({"history.01.stamp_ns": 1}, "reads 2 earlier observations"),
        ({"history.x.stamp_ns": 1}, "reads 2 earlier observations"),
        ({"history.1.image.rear": np.zeros((6, 8, 3), np.uint8)}, "reads no camera 'rear'"),
        (_huge_history_frame(), "6000x6000 is over"),
        ({"prefix": np.zeros((5, 2))}, r"at most \(4, 2\)"),
        ({"prefix": np.zeros((2, 3))}, r"at most \(4, 2\)"),
        ({"prefix": np.zeros((2, 2), np.int64)}, "not float rows"),
        ({"prefix": [[0.0, 0.0]]}, "not float rows"),
        ({"obs_tick": 1.5}, "'obs_tick': not an integer"),
        ({"obs_tick": True}, "'obs_tick': not an integer"),
        ({"inference_delay": -1}, "'inference_delay': not an integer"),
        ({"seed": 1 << 64}, "'seed': not an integer"),
        ({"seed": "7"}, "'seed': not an integer"),
    ],
)
def test_what_a_request_carries_beyond_the_policys_bounds_is_refused_from_the_header(changes, match):
    fields = _fields(**changes)
    images = ImagesRead.of(["joint_state", "images.front"])
    admit(encode(_fields()), limits=ServeLimits(), images=images, bounds=BOUNDS)  # the request itself passes
    with pytest.raises(Refused, match=match):
        admit(encode(fields), limits=ServeLimits(), images=images, bounds=BOUNDS)


def test_a_policy_without_history_or_prefix_takes_neither():
    with pytest.raises(Refused, match="reads 0 earlier observations"):
        admit(encode(_fields()), limits=ServeLimits(), images=ImagesRead.of([]))
    fields, _jpeg = request_fields(_request(history=0, prefix_rows=2), history=0, prefix_rows=4)
    with pytest.raises(Refused, match=r"at most \(0, 0\)"):
        admit(encode(fields), limits=ServeLimits(), images=ImagesRead.of([]))


class _Recording(ChunkSkill):
    """Keeps every request it is asked with."""

    def __init__(self) -> None:
        super().__init__(NAMES, chunk_size=4, observation=("joint_state", "images.front", "task"))
        self.asked: list[ChunkRequest] = []
        self._info = self._info.model_copy(update={"observation_steps": 3})

    def _chunks_impl(self, requests):
        self.asked.extend(requests)
        return super()._chunks_impl(requests)


@pytest.fixture
def recording(keys: PolicyKeys, endpoint: str) -> Iterator[_Recording]:
    skill = _Recording()
    meta = chunk_meta(skill, rate_hz=10.0, model_hash="model-a").model_copy(update={"observation_steps": 3})
    with PolicyServer(skill, keys=keys, zenoh=ZenohConfig(listen=[endpoint]), meta=meta):
        yield skill


def test_a_served_policy_is_asked_with_the_robots_history_prefix_tick_and_seed(
    recording: _Recording, client: Callable[..., Any]
):
    remote = client(deadline_ms=5000)
    assert remote.meta.observation_steps == 3
    remote.reset(seed=5)
    asked = _request(history=3, prefix_rows=6)
    remote.infer(asked, seed=11)
    got = recording.asked[-1]
    assert [w.joint_state for w in got.history] == [w.joint_state for w in asked.history[1:]]
    np.testing.assert_array_equal(got.prefix, asked.prefix[:4])
    assert (got.obs_tick, got.inference_delay, got.seed) == (41, 3, 11)
    remote.infer(_world(0.1))  # a client that does not send its seed: the one of its reset
    assert recording.asked[-1].seed == 5


def test_a_reset_seed_that_is_not_an_integer_is_refused(recording, keys, client, client_zenoh):
    client()  # the server is up
    session = open_session(client_zenoh)
    try:
        with pytest.raises(PeerError, match="'seed': not an integer"):
            request(session, keys.reset, b'{"seed": "seven"}', timeout_s=5.0)
        with pytest.raises(PeerError, match="'seed': not an integer"):
            request(session, keys.reset, b'{"seed": 1e300}', timeout_s=5.0)
    finally:
        session.close()
