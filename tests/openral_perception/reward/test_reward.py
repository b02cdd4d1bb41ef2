"""The reward monitor's ring and trend, and its client against a fake reward sidecar on Zenoh."""

from __future__ import annotations

import threading
import time

import pytest

from openral_core import ROSConfigError, ROSUnavailable
from openral_perception.reward import Frame, RollingFrameBuffer, trend


def frame(stamp_s: float, level: int = 0, width: int = 4, height: int = 2) -> Frame:
    return Frame(round(stamp_s * 1e9), bytes([level]) * (width * height * 3), width, height)


def test_the_ring_keeps_the_window_behind_the_newest_frame_and_its_size():
    ring = RollingFrameBuffer(window_s=1.0, max_frames=5, stale_after_s=0.5)
    assert ring.is_stale(0)
    for t in (0.0, 0.4, 0.8, 1.2):
        ring.push(frame(t))
    assert [f.stamp_ns for f in ring.window()] == [round(t * 1e9) for t in (0.4, 0.8, 1.2)]
    assert [f.stamp_ns for f in ring.window(0.5)] == [round(t * 1e9) for t in (0.8, 1.2)]
    for t in (1.3, 1.4, 1.5, 1.6):
        ring.push(frame(t))
    assert len(ring) == 5  # the cap, oldest first out
    assert not ring.is_stale(round(2.0 * 1e9))
    assert ring.is_stale(round(2.2 * 1e9))
    with pytest.raises(ValueError, match="older"):
        ring.push(frame(0.1))
    with pytest.raises(ValueError, match="bytes"):
        Frame(0, b"123", 4, 2)


def test_trend_is_the_least_squares_slope():
    assert trend([]) == 0.0
    assert trend([0.4]) == 0.0
    assert trend([0.0, 0.1, 0.2, 0.3]) == pytest.approx(0.1)
    assert trend([1.0, 0.0, 1.0, 0.0]) == pytest.approx(-0.2)


zenoh = pytest.importorskip("zenoh", reason="needs the 'remote' extra")

from openral_perception.reward.client import (  # noqa: E402
    RewardMonitor,
    reward_key,
    sidecar_reply,
    sidecar_request,
)
from openral_remote.config import ZenohConfig  # noqa: E402
from openral_remote.session import NoReply, RemoteTimeout, open_session  # noqa: E402
from openral_remote.testing import free_endpoint  # noqa: E402


class FakeSidecar:
    """Progress = mean brightness; success once it passes 0.8. While ``answering`` is clear, answers hang."""

    def __init__(self, endpoint: str, key: str) -> None:
        self.answering = threading.Event()
        self.answering.set()
        self.requests = 0
        self.session = open_session(ZenohConfig(listen=[endpoint]))
        self.queryable = self.session.declare_queryable(key, self._on_query, complete=True)

    def _on_query(self, query) -> None:
        self.requests += 1
        threading.Thread(target=self._answer, args=(query,), daemon=True).start()

    def _answer(self, query) -> None:
        try:
            self.answering.wait(60)
            frames, _task = sidecar_request(query.payload.to_bytes())
            progress = frames.reshape(len(frames), -1).mean(axis=1) / 255.0
            query.reply(query.key_expr, sidecar_reply(progress, (progress > 0.8).astype(float)))
        finally:
            query.drop()

    def close(self) -> None:
        self.answering.set()
        self.queryable.undeclare()
        self.session.close()


@pytest.fixture
def sidecar_and_monitor():
    endpoint = free_endpoint()
    sidecar = FakeSidecar(endpoint, reward_key("so101", "fake_reward"))
    monitor = RewardMonitor(
        model_id="fake_reward", robot="so101", zenoh=ZenohConfig(connect=[endpoint]), deadline_s=0.5
    )
    deadline = time.monotonic() + 10
    while True:  # the link is up once a request gets an answer
        try:
            monitor.score([frame(0, 10)], "warm up")
            break
        except ROSUnavailable:
            assert time.monotonic() < deadline, "the fake sidecar never answered"
            time.sleep(0.05)
    yield sidecar, monitor
    monitor.close()
    sidecar.close()


def test_a_clip_is_scored_and_assessed(sidecar_and_monitor):
    _sidecar, monitor = sidecar_and_monitor
    clip = [frame(t * 0.1, level) for t, level in enumerate((51, 102, 153, 230))]
    progress, success = monitor.score(clip, "pick the cube")
    assert progress == pytest.approx([0.2, 0.4, 0.6, 230 / 255])
    assert success == [0.0, 0.0, 0.0, 1.0]
    summary = monitor.assess(clip, "pick the cube")
    assert summary["succeeded"] is True
    assert summary["stalled"] is False
    assert summary["progress_trend"] > 0.2
    assert summary["frames_seen"] == 4
    flat = monitor.assess([frame(t * 0.1, 40) for t in range(5)], "pick the cube")
    assert flat["stalled"] is True


def test_a_hung_sidecar_costs_one_request_and_the_next_one_works(sidecar_and_monitor):
    sidecar, monitor = sidecar_and_monitor
    sidecar.answering.clear()  # hung until released
    started = time.perf_counter()
    with pytest.raises(RemoteTimeout):
        monitor.score([frame(0, 100)], "pick")
    assert time.perf_counter() - started < 5.0  # the 0.5 s deadline, not the hang
    sidecar.answering.set()  # the hung request's late answer goes out too
    progress, _success = monitor.score([frame(0, 255)], "pick")  # not wedged by the timeout
    assert progress == [1.0]


def test_bad_clips_are_refused_before_anything_is_sent(sidecar_and_monitor):
    sidecar, monitor = sidecar_and_monitor
    before = sidecar.requests
    with pytest.raises(ROSConfigError, match="empty clip"):
        monitor.score([], "pick")
    with pytest.raises(ROSConfigError, match="one size"):
        monitor.score([frame(0, 1), frame(0.1, 1, width=8)], "pick")
    with pytest.raises(ROSConfigError, match="task"):
        monitor.score([frame(0, 1)], "  ")
    assert sidecar.requests == before


def test_without_a_sidecar_a_request_fails_fast():
    monitor = RewardMonitor(
        model_id="nobody", robot="so101", zenoh=ZenohConfig(connect=[free_endpoint()]), deadline_s=30
    )
    try:
        started = time.perf_counter()
        with pytest.raises(NoReply, match="nobody"):
            monitor.score([frame(0, 1)], "pick")
        assert time.perf_counter() - started < 10.0  # at once, not after the 30 s deadline
    finally:
        monitor.close()


def test_a_reward_manifest_builds_its_monitor_and_other_kinds_are_refused():
    from openral_perception.reward.client import build_reward_monitor  # noqa: PLC0415
    from openral_rskill.manifest import RSkillManifest  # noqa: PLC0415

    manifest = RSkillManifest(
        name="progress_model", kind="reward", license="Apache-2.0", reward={"success_threshold": 0.7, "deadline_s": 1}
    )
    monitor = build_reward_monitor(manifest, robot="so101", zenoh=ZenohConfig(connect=[free_endpoint()]))
    try:
        assert monitor.key == "openral/so101/reward/progress_model/score"
        assert monitor.success_threshold == 0.7
        assert monitor.deadline_s == 1
    finally:
        monitor.close()
    policy = RSkillManifest(name="hello", skill="hello", license="Apache-2.0")
    with pytest.raises(ROSConfigError, match="not a reward"):
        build_reward_monitor(policy, robot="so101", zenoh=ZenohConfig())
