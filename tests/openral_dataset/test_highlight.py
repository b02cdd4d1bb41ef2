"""Highlights: the last N seconds held in memory, compressed, and committed as an episode when asked."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq
import pytest
from structlog.testing import capture_logs

from openral_core import (
    FrameEncoding,
    JointState,
    ObserverContext,
    RobotEnvironment,
    ROSConfigError,
    ROSRuntimeError,
    SensorFrame,
    TickResult,
    WorldState,
)
from openral_dataset import layout, schema
from openral_dataset.check import check_dataset
from openral_dataset.highlight import MAX_HIGHLIGHT_S, HeldFrame, HighlightRing
from openral_dataset.recorder import RolloutRecorder
from openral_dataset.testing import numbered_pixels, read_number
from openral_dataset.video import StreamingVideoEncoder
from openral_dataset.writer import LeRobotDatasetSink, read_tasks
from openral_hal.manifests import load_robot_manifest

JOINTS = ["j0", "j1", "j2"]
FPS = 30
W, H = 64, 48
HIGHLIGHT_S = 0.5
HELD = 15  # HIGHLIGHT_S x FPS rows


def _pixels(number: int) -> np.ndarray:
    """The number's blocks over a colour gradient: content a codec must keep in place and in colour."""
    image = numbered_pixels(number, W, H)
    image[..., 0] = np.maximum(image[..., 0], np.linspace(0, 180, W, dtype=np.uint8)[None, :])
    image[..., 2] = np.maximum(image[..., 2], np.linspace(0, 120, H, dtype=np.uint8)[:, None])
    return image


def _world(i: int) -> WorldState:
    stamp = (i + 1) * 33_333_333
    frame = SensorFrame(
        sensor_id="front", stamp_ns=stamp, width=W, height=H, seq=i, encoding=FrameEncoding.RGB8, data=_pixels(i)
    )
    joints = JointState(names=JOINTS, positions=[float(i), 0.0, 0.0], stamp_ns=stamp)
    return WorldState(stamp_ns=stamp + 1_000_000, joint_state=joints, image_frames={"front": frame})


def _tick(i: int) -> TickResult:
    return TickResult(tick_idx=i, start_ns=(i + 1) * 33_333_333, step_idx=i, action_applied=True, sent_action=[i, 1, 2])


def _recorder(root: Path, highlight_s: float = HIGHLIGHT_S) -> RolloutRecorder:
    sink = LeRobotDatasetSink(
        root, fps=FPS, robot_type="arm", joint_names=JOINTS, cameras=[schema.CameraSpec("front", W, H)], vcodec="h264"
    )
    return RolloutRecorder(sink, joint_names=JOINTS, highlight_s=highlight_s)


def _feed(recorder: RolloutRecorder, ticks: range) -> None:
    """Hand ``ticks`` over and wait until the worker has taken every one (a save holds what it has taken)."""
    for i in ticks:
        recorder.on_tick(_tick(i), _world(i))
        recorder.wait_for_room()
    deadline = time.monotonic() + 30
    while recorder.handled < ticks.stop:
        assert time.monotonic() < deadline, "the recorder's worker did not take the ticks"
        time.sleep(0.001)


def _table(root: Path, episode: int) -> dict[str, list[object]]:
    return pq.read_table(layout.data_file(root, episode)).to_pydict()


def _video(root: Path, episode: int) -> list[np.ndarray]:
    with av.open(str(layout.video_file(root, schema.video_key("front"), episode))) as container:
        return [f.to_ndarray(format="rgb24") for f in container.decode(container.streams.video[0])]


def test_a_save_commits_exactly_the_last_n_seconds_with_their_frames(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    recorder = _recorder(root)
    recorder.on_episode_start(0, "pick the cube")
    _feed(recorder, range(100))
    assert not (root / layout.INFO_PATH).exists()  # nothing written while the episode runs
    assert recorder.report()["highlight_rows"] == HELD

    saved: list[object] = []
    caller = threading.Thread(target=lambda: saved.append(recorder.save_highlight().result(60)))  # any thread
    caller.start()
    caller.join(60)
    summary = saved[0]
    assert summary is not None
    assert summary == recorder.episodes[0]
    assert (summary.episode_idx, summary.frames, summary.task, summary.committed) == (0, HELD, "pick the cube", True)

    _feed(recorder, range(100, 120))  # the ring keeps filling after a save
    second = recorder.save_highlight().result(60)
    assert second is not None
    assert (second.episode_idx, second.frames) == (1, HELD)
    recorder.on_episode_end(0, success=True)
    recorder.close()

    assert recorder.errors == 0
    checked = check_dataset(root)
    assert checked.problems == []
    assert (checked.episodes, checked.frames, checked.videos) == (2, 2 * HELD, 2)
    assert read_tasks(root) == {"pick the cube": 0}
    for episode, last in enumerate([100, 120]):
        table = _table(root, episode)
        expected = list(range(last - HELD, last))
        assert table["openral.tick_idx"] == expected
        assert table["openral.front.seq"] == expected
        assert [s[0] for s in table["observation.state"]] == expected
        assert [a[0] for a in table["action"]] == expected
        assert table["frame_index"] == list(range(HELD))
        assert table["timestamp"] == pytest.approx([i / FPS for i in range(HELD)])
        assert table["index"] == list(range(episode * HELD, (episode + 1) * HELD))
        frames = _video(root, episode)
        assert [read_number(f) for f in frames] == expected
        for tick, frame in zip(expected, frames, strict=True):  # JPEG then H.264: close, not exact
            error = np.abs(frame.astype(np.int16) - _pixels(tick).astype(np.int16))
            assert float(error.mean()) < 6.0


def test_episode_end_forgets_the_ring_and_an_empty_save_writes_nothing(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    recorder = _recorder(root)
    with capture_logs() as logs:
        assert recorder.save_highlight().result(10) is None  # no episode open
        recorder.on_episode_start(0, "pick")
        _feed(recorder, range(40))
        recorder.on_episode_end(0, success=True)
        assert recorder.wait_for_commit(30)
        assert recorder.report()["highlight_rows"] == 0
        assert recorder.save_highlight().result(10) is None
        recorder.on_episode_start(1, "pick")
        assert recorder.save_highlight().result(10) is None  # open, but nothing held yet
    recorder.close()
    warnings = [e for e in logs if e["log_level"] == "warning"]
    assert [e["event"] for e in warnings] == ["highlight not saved"] * 3
    assert recorder.episodes == []
    assert not (root / layout.INFO_PATH).exists()
    assert check_dataset(root).episodes == 0


def test_the_ring_stays_bounded_when_fed_far_more_than_n_seconds(tmp_path: Path) -> None:
    recorder = _recorder(tmp_path / "ds")
    recorder.on_episode_start(0, "pick")
    held: list[tuple[int, int]] = []
    for block in range(10):  # ten times what the ring holds
        _feed(recorder, range(block * HELD, (block + 1) * HELD))
        report = recorder.report()
        held.append((report["highlight_rows"], report["highlight_bytes"]))
    recorder.close()
    assert recorder.report()["highlight_capacity_rows"] == HELD
    assert {rows for rows, _ in held} == {HELD}
    sizes = [size for _, size in held]
    assert max(sizes) < 1.2 * min(sizes)  # flat: the oldest rows go as new ones come
    assert max(sizes) < HELD * W * H * 3  # below the raw frames alone: held compressed


def test_a_failed_save_stops_recording_and_keeps_the_saved_highlights(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = tmp_path / "ds"
    recorder = _recorder(root)
    stops: list[str] = []
    recorder.on_failure = lambda: stops.append("stop")
    recorder.on_episode_start(0, "pick")
    _feed(recorder, range(30))
    assert recorder.save_highlight().result(60) is not None

    def dying(self: StreamingVideoEncoder, frame: SensorFrame | None) -> bool:
        raise ROSRuntimeError("the video encoder of camera front exited (-9)")

    monkeypatch.setattr(StreamingVideoEncoder, "add", dying)
    with pytest.raises(ROSRuntimeError, match="encoder of camera front exited"):
        recorder.save_highlight().result(60)
    assert recorder.failure is not None
    assert str(root) in str(recorder.failure)
    assert stops == ["stop"]
    assert recorder.save_highlight().result(10) is None  # stopped: nothing more is saved
    recorder.close()
    checked = check_dataset(root)
    assert checked.problems == []
    assert (checked.episodes, checked.frames) == (1, HELD)


# -- held frames ------------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", [FrameEncoding.RGB8, FrameEncoding.BGR8, FrameEncoding.RGBA8])
def test_a_held_frame_comes_back_as_rgb_in_the_right_channel_order(encoding: FrameEncoding) -> None:
    rgb = _pixels(1234)
    data = {
        FrameEncoding.RGB8: rgb,
        FrameEncoding.BGR8: np.ascontiguousarray(rgb[..., ::-1]),
        FrameEncoding.RGBA8: np.concatenate([rgb, np.full((H, W, 1), 255, np.uint8)], axis=2),
    }[encoding]
    data.flags.writeable = False  # capture buffers may be read-only
    frame = SensorFrame(sensor_id="front", stamp_ns=5, width=W, height=H, seq=9, encoding=encoding, data=data)
    held = HeldFrame.compress(frame)
    assert len(held.jpeg) < rgb.nbytes
    back = held.restore()
    assert (back.sensor_id, back.stamp_ns, back.seq, back.encoding) == ("front", 5, 9, FrameEncoding.RGB8)
    error = np.abs(back.as_array().astype(np.int16) - rgb.astype(np.int16))
    assert float(error.mean()) < 3.0
    assert read_number(back.as_array()) == 1234


def test_a_grey_frame_stays_grey_and_a_depth_frame_is_refused() -> None:
    grey = np.ascontiguousarray(_pixels(77)[..., 1])
    frame = SensorFrame(sensor_id="g", stamp_ns=1, width=W, height=H, encoding=FrameEncoding.MONO8, data=grey)
    back = HeldFrame.compress(frame).restore()
    assert back.encoding is FrameEncoding.MONO8
    assert float(np.abs(back.as_array().astype(np.int16) - grey).mean()) < 3.0
    depth = SensorFrame(
        sensor_id="d", stamp_ns=1, width=W, height=H, encoding=FrameEncoding.MONO16, data=np.zeros((H, W), np.uint16)
    )
    with pytest.raises(ROSRuntimeError, match="mono16"):
        HeldFrame.compress(depth)


def test_the_ring_holds_the_newest_rows_and_forgets_them_at_stop() -> None:
    ring = HighlightRing(3)
    ring.push({"n": -1}, {})  # outside an episode: not held
    assert ring.snapshot() is None
    ring.start("pick")
    frame = _world(0).image_frames["front"]  # type: ignore[index]
    for n in range(5):
        ring.push({"n": n}, {"front": frame if n % 2 else None})
    snapshot = ring.snapshot()
    assert snapshot is not None
    assert snapshot.task == "pick"
    assert [r.row["n"] for r in snapshot.rows] == [2, 3, 4]
    assert [sorted(r.frames) for r in snapshot.rows] == [[], ["front"], []]  # a missing frame is repeated later
    assert ring.rows == 3
    assert ring.nbytes == sum(r.nbytes for r in snapshot.rows)
    assert ring.frames_compressed == 2
    ring.stop()
    assert (ring.rows, ring.nbytes, ring.snapshot()) == (0, 0, None)
    assert [r.row["n"] for r in snapshot.rows] == [2, 3, 4]  # a snapshot keeps its rows
    ring.close()
    ring.close()  # idempotent


def test_compressing_into_a_file_gives_the_same_bytes_as_into_memory() -> None:
    # Pillow encodes without the interpreter lock only into a real file: the ring's scratch file.
    frame = _world(3).image_frames["front"]  # type: ignore[index]
    ring = HighlightRing(1)
    try:
        assert ring._scratch is not None  # Linux: an in-memory file
        assert HeldFrame.compress(frame, scratch=ring._scratch) == HeldFrame.compress(frame)
        assert HeldFrame.compress(frame, scratch=ring._scratch) == HeldFrame.compress(frame)  # reused
    finally:
        ring.close()


# -- parameters ------------------------------------------------------------------------------


def _deployment() -> RobotEnvironment:
    return RobotEnvironment.model_validate(
        {
            "hal": {"robot_id": "so101_follower", "adapter": "null"},
            "vla": {"id": "noop"},
            "rate_hz": 30.0,
            "sensors": [{"sensor_id": "front", "width": W, "height": H}],
        }
    )


def test_from_config_takes_highlight_s(tmp_path: Path) -> None:
    recorder = RolloutRecorder.from_config(
        {"root": "ds", "highlight_s": 30},
        ObserverContext.of_deployment(_deployment(), load_robot_manifest("so101_follower"), tmp_path),
    )
    try:
        assert recorder.highlight is not None
        assert recorder.highlight.capacity_rows == 900
        assert recorder.part_rows is None
        assert recorder.report()["highlight_capacity_rows"] == 900
    finally:
        recorder.close()


@pytest.mark.parametrize("value", [0, -1.0, float("inf"), float("nan"), "30", MAX_HIGHLIGHT_S + 1, 1e9])
def test_a_bad_highlight_s_names_the_field(tmp_path: Path, value: object) -> None:
    with pytest.raises(ROSConfigError, match=r"observers\[\]\.params\.highlight_s"):
        RolloutRecorder.from_config(
            {"root": "ds", "highlight_s": value},
            ObserverContext.of_deployment(_deployment(), load_robot_manifest("so101_follower"), tmp_path),
        )


def test_highlights_and_continuous_recording_together_are_refused_naming_both(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match="highlight_s and episode_every_s"):
        RolloutRecorder.from_config(
            {"root": "ds", "highlight_s": 30, "episode_every_s": 60},
            ObserverContext.of_deployment(_deployment(), load_robot_manifest("so101_follower"), tmp_path),
        )
    sink = LeRobotDatasetSink(tmp_path / "ds", fps=FPS, robot_type="arm", joint_names=JOINTS, defer_open=True)
    with pytest.raises(ROSConfigError, match="highlight_s and episode_every_s"):
        RolloutRecorder(sink, joint_names=JOINTS, highlight_s=30, episode_every_s=60)
    with pytest.raises(ROSConfigError, match="shorter than one frame") as short:
        RolloutRecorder(sink, joint_names=JOINTS, highlight_s=0.01)
    assert short.value.field == "highlight_s"
    assert not (tmp_path / "ds").exists()


def test_the_longest_highlight_closes_in_time_and_a_longer_one_is_refused(tmp_path: Path) -> None:
    sink = LeRobotDatasetSink(tmp_path / "ds", fps=FPS, robot_type="arm", joint_names=JOINTS, defer_open=True)
    with pytest.raises(ROSConfigError, match="at most 600 s") as long:
        RolloutRecorder(sink, joint_names=JOINTS, highlight_s=1e9)
    assert long.value.field == "highlight_s"
    recorder = RolloutRecorder(sink, joint_names=JOINTS, highlight_s=MAX_HIGHLIGHT_S)
    assert recorder.highlight is not None
    assert recorder.highlight.capacity_rows == MAX_HIGHLIGHT_S * FPS
    assert recorder.wait_for_commit(timeout_s=1e12)  # any wait is cut to what a thread wait takes
    with capture_logs() as logs:
        recorder.close()
    assert [entry for entry in logs if entry["log_level"] in ("warning", "error")] == []
    assert not recorder._thread.is_alive()  # its worker was joined


def test_save_highlight_needs_highlight_mode(tmp_path: Path) -> None:
    sink = LeRobotDatasetSink(tmp_path / "ds", fps=FPS, robot_type="arm", joint_names=JOINTS, defer_open=True)
    recorder = RolloutRecorder(sink, joint_names=JOINTS)
    try:
        with pytest.raises(ROSRuntimeError, match="highlight_s"):
            recorder.save_highlight()
    finally:
        recorder.close()
