"""One server, many robots (and hostile peers): episodes per client, requests checked unread, fair turns, batches."""

import io
import json
import threading
import time
import uuid
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from PIL import Image

from openral_core import JointState, WorldState
from openral_observability import semconv
from openral_remote.admission import ServeLimits
from openral_remote.codec import encode
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.server import PolicyServer
from openral_remote.session import PeerError, open_session, request
from openral_remote.testing import ChunkSkill, chunk_meta, wait_for

pytestmark = pytest.mark.timeout(120)

NAMES = ["a0", "a1"]


def _world(q: tuple[float, float]) -> WorldState:
    return WorldState(stamp_ns=1, joint_state=JointState(names=NAMES, positions=list(q)))


class _Built:
    """Every ChunkSkill a server made, and how many were configured."""

    def __init__(self, **kwargs: object) -> None:
        self.kwargs = kwargs
        self.skills: list[ChunkSkill] = []

    def __call__(self) -> ChunkSkill:
        skill = ChunkSkill(NAMES, **self.kwargs)  # type: ignore[arg-type]
        self.skills.append(skill)
        return skill

    @property
    def configured(self) -> int:
        return sum(skill.state.value != "unconfigured" for skill in self.skills)


@pytest.fixture
def serve(keys: PolicyKeys, endpoint: str) -> Iterator[Callable[..., tuple[PolicyServer, _Built]]]:
    servers: list[PolicyServer] = []

    def start(limits: ServeLimits | None = None, **kwargs: object) -> tuple[PolicyServer, _Built]:
        built = _Built(**kwargs)
        first = built()
        meta = chunk_meta(first, rate_hz=10.0, model_hash="model-a")
        server = PolicyServer(
            first, keys=keys, zenoh=ZenohConfig(listen=[endpoint]), meta=meta, limits=limits, factory=built
        )
        server.start()
        servers.append(server)
        return server, built

    yield start
    for server in servers:
        server.close()


def test_a_reset_from_one_robot_leaves_another_robots_episode_alone(serve, client):
    _server, built = serve(latch=True)  # each episode plans from where it started
    a, b = client(), client()
    a.reset(seed=1)
    assert a.infer(_world((0.0, 0.0)))[0, 0] == pytest.approx(0.5)  # a's episode starts at 0.0
    b.reset(seed=2)
    assert b.infer(_world((1.54, 0.0)))[0, 0] == pytest.approx(1.54 + 0.5)  # b's starts at 1.54
    assert a.infer(_world((0.0, 0.0)))[0, 0] == pytest.approx(0.5)  # a's plan is untouched by b's reset
    b.reset(seed=3)  # only b's episode restarts
    assert b.infer(_world((0.2, 0.0)))[0, 0] == pytest.approx(0.7)
    assert a.infer(_world((0.9, 0.0)))[0, 0] == pytest.approx(0.5)
    seeds = sorted(skill.seeds for skill in built.skills if skill.seeds)
    assert seeds == [[1], [2, 3]]  # each robot's resets reached its own instance only


def test_a_policy_without_episode_state_is_loaded_once_for_every_robot(serve, client):
    server, built = serve()
    robots = [client() for _ in range(3)]
    for i, remote in enumerate(robots):
        remote.reset(seed=i)
        assert remote.infer(_world((float(i), 0.0)))[0, 0] == pytest.approx(i + 0.5)
    assert built.configured == 1
    assert server.clients == 3


def _jpeg(width: int, height: int) -> bytes:
    out = io.BytesIO()
    Image.new("RGB", (width, height), (90, 90, 90)).save(out, format="JPEG", quality=10)
    return out.getvalue()


def _hostile_request(width: int, height: int, sensor: str = "front") -> bytes:
    """An observation carrying a JPEG that announces its true (huge) size: small on the wire, costly to decode."""
    header_fields = {
        "stamp_ns": 1,
        f"image.{sensor}": np.frombuffer(_jpeg(width, height), dtype=np.uint8),
        f"image.{sensor}.meta": {
            "encoding": "jpeg",
            "width": width,
            "height": height,
            "stamp_ns": 1,
            "seq": 0,
            "frame_id": None,
        },
    }
    return encode(header_fields)


def _rss_mib() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_a_huge_image_is_refused_unread_and_leaves_no_memory_behind(serve, client, keys, client_zenoh):
    server, built = serve(observation=())  # reads everything, images included
    remote = client()
    remote.infer(_world((0.0, 0.0)))
    message = _hostile_request(6000, 6000)
    assert len(message) < 1 << 20  # a small request...
    session = open_session(client_zenoh)
    try:
        baseline = _rss_mib()
        for _ in range(30):
            attachment = json.dumps({"client": uuid.uuid4().hex}).encode()
            with pytest.raises(PeerError, match="6000x6000 is over"):
                request(session, keys.infer, message, timeout_s=5.0, attachment=attachment)
        grown = _rss_mib() - baseline
    finally:
        session.close()
    assert server.stats.refused == 30
    assert server.stats.errors == 0
    assert built.skills[0].batch_sizes == [1]  # the policy never saw one
    assert grown < 40  # 30 decodes of 6000x6000 RGB would hold gigabytes
    assert remote.infer(_world((0.3, 0.0)))[0, 0] == pytest.approx(0.8)


def test_an_image_of_a_camera_the_policy_does_not_read_is_refused(serve, keys, client_zenoh):
    server, _built = serve(observation=("joint_state",))
    session = open_session(client_zenoh)
    try:
        deadline = time.monotonic() + 20
        while not list(session.liveliness().get(keys.alive, timeout=1.0)) and time.monotonic() < deadline:
            pass
        with pytest.raises(PeerError, match="reads no camera 'front'"):
            request(session, keys.infer, _hostile_request(64, 48), timeout_s=5.0)
    finally:
        session.close()
    assert server.stats.refused == 1


def test_a_jpeg_whose_own_size_differs_from_its_description_is_refused(serve, client, keys, client_zenoh):
    _server, built = serve(observation=())
    client()  # the server is up
    fields = {
        "stamp_ns": 1,
        "image.front": np.frombuffer(_jpeg(4000, 3000), dtype=np.uint8),
        "image.front.meta": {"encoding": "jpeg", "width": 64, "height": 48, "stamp_ns": 1, "seq": 0},
    }
    session = open_session(client_zenoh)
    try:
        with pytest.raises(PeerError, match="4000x3000 described as 64x48"):
            request(session, keys.infer, encode(fields), timeout_s=5.0)
    finally:
        session.close()
    assert built.skills[0].batch_sizes == []


def test_a_flood_under_fresh_client_ids_does_not_starve_a_robot_under_way(serve, client, keys, client_zenoh):
    limits = ServeLimits(max_pending=4, max_clients=4096)
    server, _built = serve(limits=limits, delay_s=0.02)
    remote = client(deadline_ms=3000)
    remote.infer(_world((0.0, 0.0)))  # the robot is under way
    stop = threading.Event()
    attacker = open_session(client_zenoh)
    message = encode({"stamp_ns": 1, "joint.names": NAMES, "joint.positions": np.zeros(2)})

    def flood() -> None:
        while not stop.is_set():
            attachment = json.dumps({"client": uuid.uuid4().hex}).encode()
            replies = attacker.get(keys.infer, payload=message, attachment=attachment, timeout=5.0)
            threading.Thread(target=lambda r=replies: list(r), daemon=True).start()
            time.sleep(0.002)

    flooders = [threading.Thread(target=flood, daemon=True) for _ in range(3)]
    for thread in flooders:
        thread.start()
    try:
        assert wait_for(lambda: server.stats.refused > 20)  # the queue is full and newcomers are turned away
        served = 0
        for i in range(15):
            chunk = remote.infer(_world((0.01 * i, 0.0)))  # every request answered, none refused or late
            assert chunk[0, 0] == pytest.approx(0.01 * i + 0.5)
            served += 1
    finally:
        stop.set()
        for thread in flooders:
            thread.join()
        attacker.close()
    assert served == 15


def test_concurrent_robots_are_batched_and_each_gets_its_own_chunk(serve, client, telemetry):
    limits = ServeLimits(max_batch=8, max_wait_ms=200.0)
    server, built = serve(limits=limits, batch=8, delay_s=0.05)
    robots = [client(deadline_ms=5000) for _ in range(4)]
    for remote in robots:
        remote.infer(_world((0.0, 0.0)))  # all four are active clients now
    results: dict[int, np.ndarray] = {}
    start = threading.Barrier(len(robots))

    def ask(i: int) -> None:
        start.wait()
        results[i] = robots[i].infer(_world((float(i), 0.0)))

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(len(robots))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for i, chunk in results.items():
        assert chunk[0, 0] == pytest.approx(i + 0.5)
    assert max(built.skills[0].batch_sizes) > 1
    assert server.stats.largest_batch > 1
    sizes = [span.attributes[semconv.ATTR_REMOTE_BATCH_SIZE] for span in telemetry.spans(semconv.SPAN_REMOTE_INFER)]
    assert max(sizes) > 1


def test_one_failing_request_in_a_batch_fails_alone(serve, client, keys, client_zenoh):
    limits = ServeLimits(max_batch=8, max_wait_ms=300.0)
    _server, _built = serve(limits=limits, batch=8, delay_s=0.02)
    honest = client(deadline_ms=5000)
    honest.infer(_world((0.0, 0.0)))
    session = open_session(client_zenoh)
    try:
        bad = encode({"stamp_ns": "not a number"})
        outcome: dict[str, object] = {}

        def ask_bad() -> None:
            try:
                request(session, keys.infer, bad, timeout_s=5.0, attachment=b'{"client": "x"}')
            except PeerError as exc:
                outcome["bad"] = exc.text

        thread = threading.Thread(target=ask_bad)
        thread.start()
        chunk = honest.infer(_world((0.4, 0.0)))
        thread.join()
    finally:
        session.close()
    assert chunk[0, 0] == pytest.approx(0.9)
    assert "bad request" in str(outcome["bad"])


def test_a_zenoh_peer_without_a_client_id_has_an_episode_of_its_own(serve, client, keys, client_zenoh):
    _server, _built = serve(latch=True)
    remote = client()
    remote.infer(_world((0.2, 0.0)))
    session = open_session(client_zenoh)
    try:
        message = encode({"stamp_ns": 1, "joint.names": NAMES, "joint.positions": np.array([1.0, 0.0])})
        request(session, keys.reset, b'{"seed": 5}', timeout_s=5.0)
        request(session, keys.infer, message, timeout_s=5.0)
    finally:
        session.close()
    assert remote.infer(_world((0.0, 0.0)))[0, 0] == pytest.approx(0.7)
