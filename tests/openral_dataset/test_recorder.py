"""Recording through the runner: rows, frames and episodes land in a LeRobotDataset v3.0 that checks clean."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq
import pytest
from structlog.testing import capture_logs

from openral_core import (
    CameraSize,
    FrameEncoding,
    JointState,
    ObserverContext,
    RobotEnvironment,
    ROSConfigError,
    ROSRuntimeError,
    SensorFrame,
    SensorReaderConfig,
    TickResult,
    WorldState,
)
from openral_dataset import layout, schema
from openral_dataset.check import check_dataset
from openral_dataset.recorder import RolloutRecorder
from openral_dataset.testing import numbered_pixels, read_number
from openral_dataset.video import OverflowPolicy, StreamingVideoEncoder
from openral_dataset.writer import LeRobotDatasetSink, read_tasks
from openral_hal.manifests import load_robot_manifest
from openral_hal.testing import RecordingHAL
from openral_rskill.testing import ScriptedSkill
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import FakeClock
from openral_world_state import WorldStateAggregator

JOINTS = ["j0", "j1", "j2"]
FPS = 30
W, H = 64, 48


class NumberedReader:
    """A camera whose n-th capture shows the number n (a real reader's five protocol members)."""

    def __init__(self, sensor_id: str, clock: FakeClock) -> None:
        self.sensor_id = sensor_id
        self.clock = clock
        self.seq = 0
        self._open = False

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def read_latest(self, max_age_ms: float | None = None) -> SensorFrame:
        self.seq += 1
        return SensorFrame(
            sensor_id=self.sensor_id,
            stamp_ns=self.clock.now_ns() - 2_000_000,
            width=W,
            height=H,
            encoding=FrameEncoding.RGB8,
            seq=self.seq,
            data=numbered_pixels(self.seq, W, H),
        )


def _runner(tmp_path: Path, clock: FakeClock, *, resume: bool = False) -> tuple[HardwareRunner, RolloutRecorder]:
    sink = LeRobotDatasetSink(
        tmp_path / "ds",
        fps=FPS,
        robot_type="so101_follower",
        joint_names=JOINTS,
        cameras=[schema.CameraSpec("front", W, H)],
        vcodec="h264",
        resume=resume,
    )
    recorder = RolloutRecorder(sink, joint_names=JOINTS)
    skill = ScriptedSkill(JOINTS, actions=[[0.1 * i, 0.0, 0.0] for i in range(1, 200)])
    skill.configure()
    skill.activate()
    aggregator = WorldStateAggregator(sensors=[SensorReaderConfig(sensor_id="front")], clock=clock.now_ns)
    runner = HardwareRunner(
        hal=RecordingHAL(JOINTS, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=aggregator,
        sensor_readers=[NumberedReader("front", clock)],
        rate_hz=FPS,
        clock=clock,
        thumbnail_hz=0.0,
        recorder=recorder,
    )
    return runner, recorder


def _decode(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as container:
        return [frame.to_ndarray(format="rgb24") for frame in container.decode(container.streams.video[0])]


def test_three_episodes_two_tasks_record_the_frames_the_skill_saw(tmp_path: Path) -> None:
    clock = FakeClock()
    runner, recorder = _runner(tmp_path, clock)
    runner.activate()
    lengths = [5, 9, 7]
    tasks = ["pick the cube", "place the cube", "pick the cube"]
    for length, task in zip(lengths, tasks, strict=True):
        runner.episode_start(task)
        runner.run(length)
        runner.episode_end(success=True)
    runner.run(3)  # between episodes: nothing is recorded
    runner.deactivate()
    assert recorder.errors == 0
    assert [e.frames for e in recorder.episodes] == lengths

    root = tmp_path / "ds"
    report = check_dataset(root)
    assert report.problems == []
    assert (report.episodes, report.frames, report.videos) == (3, 21, 3)
    assert read_tasks(root) == {"pick the cube": 0, "place the cube": 1}
    for episode, length in enumerate(lengths):
        table = pq.read_table(layout.data_file(root, episode)).to_pydict()
        assert table["timestamp"] == pytest.approx([i / FPS for i in range(length)])
        frames = _decode(layout.video_file(root, schema.video_key("front"), episode))
        assert len(frames) == length
        # Row k's video frame is the very frame the skill saw: its number is the recorded capture sequence.
        assert [read_number(f) for f in frames] == table["openral.front.seq"]
        assert all(table["openral.action_applied"])
        np.testing.assert_allclose(table["action"], table["openral.requested_action"])
        assert table["task_index"] == [0 if tasks[episode] == "pick the cube" else 1] * length


def test_a_discarded_take_leaves_no_trace(tmp_path: Path) -> None:
    clock = FakeClock()
    runner, _recorder = _runner(tmp_path, clock)
    runner.activate()
    runner.episode_start("take one")
    runner.run(4)
    runner.episode_end(success=False, keep=False)
    runner.episode_start("take two")
    runner.run(6)
    runner.episode_end(success=True)
    runner.deactivate()
    root = tmp_path / "ds"
    assert check_dataset(root).problems == []
    assert read_tasks(root) == {"take two": 0}
    table = pq.read_table(layout.data_file(root, 0)).to_pydict()
    assert len(table["index"]) == 6
    seqs = table["openral.front.seq"]
    assert seqs == list(range(seqs[0], seqs[0] + 6))  # none of the discarded take's frames
    assert not (root / layout.STAGING_DIR).exists()


def test_resume_continues_the_index_and_refuses_a_different_robot(tmp_path: Path) -> None:
    clock = FakeClock()
    runner, _ = _runner(tmp_path, clock)
    runner.activate()
    runner.episode_start("pick")
    runner.run(5)
    runner.episode_end(success=True)
    runner.deactivate()
    with pytest.raises(ROSConfigError, match="--resume"):
        _runner(tmp_path, clock)
    runner, _ = _runner(tmp_path, clock, resume=True)
    runner.activate()
    runner.episode_start("pick")
    runner.run(4)
    runner.episode_end(success=True)
    runner.deactivate()
    report = check_dataset(tmp_path / "ds")
    assert report.problems == []
    assert (report.episodes, report.frames) == (2, 9)
    with pytest.raises(ROSConfigError, match="features differ"):
        LeRobotDatasetSink(tmp_path / "ds", fps=FPS, robot_type="x", joint_names=["a"], resume=True)


def test_replay_finds_a_rows_tick_and_the_frame_the_skill_saw(tmp_path: Path) -> None:
    from click.testing import CliRunner  # noqa: PLC0415

    from openral_cli.main import cli  # noqa: PLC0415
    from openral_dataset.replay import lookup_frame  # noqa: PLC0415

    clock = FakeClock()
    runner, _ = _runner(tmp_path, clock)
    runner.activate()
    runner.episode_start("pick")
    runner.run(6)
    runner.episode_end(success=True)
    runner.deactivate()
    root = tmp_path / "ds"
    found = lookup_frame(root, 0, 4)
    assert found.row["frame_index"] == 4
    assert read_number(found.images["front"]) == found.row["openral.front.seq"]
    assert found.row["openral.tick_idx"] == runner.recent_ticks[4].tick_idx

    result = CliRunner().invoke(cli, ["replay", "--frame", f"{root}/0/4", "--out", str(tmp_path / "png")])
    assert result.exit_code == 0, result.output
    assert f"openral.front.seq                {found.row['openral.front.seq']}" in result.output
    assert (tmp_path / "png" / "front_episode0_frame4.png").exists()
    missing = CliRunner().invoke(cli, ["replay", "--frame", f"{root}/0/6"])
    assert missing.exit_code == 2
    assert "0..5" in missing.output


def test_the_first_write_failure_stops_recording_and_keeps_the_committed_episodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    clock = FakeClock()
    runner, recorder = _runner(tmp_path, clock)
    stops: list[str] = []
    recorder.on_failure = lambda: stops.append("stop")
    runner.activate()
    runner.episode_start("pick")
    runner.run(5)
    runner.episode_end(success=True)
    assert recorder.wait_for_commit(30)

    real_add = StreamingVideoEncoder.add
    frames = iter(range(1000))

    def dying(self: StreamingVideoEncoder, frame: SensorFrame | None) -> bool:
        if next(frames) == 3:
            raise ROSRuntimeError("the video encoder of camera front exited (-9)")
        return real_add(self, frame)

    monkeypatch.setattr(StreamingVideoEncoder, "add", dying)
    with capture_logs() as logs:
        runner.episode_start("pick")
        runner.run(8)  # every tick after the failure would have failed too
        runner.episode_end(success=True)
        runner.episode_start("pick")  # nothing more is recorded
        runner.run(4)
        runner.episode_end(success=True)
        runner.deactivate()

    assert recorder.failure is not None
    assert str(tmp_path / "ds") in str(recorder.failure)
    assert "encoder of camera front exited" in str(recorder.failure)
    assert stops == ["stop"]
    assert recorder.errors == 1
    errors = [e for e in logs if e["log_level"] == "error"]
    assert [e["event"] for e in errors] == ["recording stopped"]
    assert "exc_info" not in errors[0]  # one line; the traceback only at debug level
    report = check_dataset(tmp_path / "ds")
    assert report.problems == []
    assert (report.episodes, report.frames) == (1, 5)


# -- the lerobot_dataset observer: built from a deployment, opened at start --------------------------


def _deployment(rate_hz: float = 30.0) -> RobotEnvironment:
    return RobotEnvironment.model_validate(
        {
            "hal": {"robot_id": "so101_follower", "adapter": "null"},
            "vla": {"id": "noop"},
            "rate_hz": rate_hz,
            "sensors": [{"sensor_id": "front", "width": W, "height": H}, {"sensor_id": "wrist"}],
        }
    )


def test_from_config_builds_the_cli_recording_and_opens_nothing_until_start(tmp_path: Path) -> None:
    robot = load_robot_manifest("so101_follower")
    recorder = RolloutRecorder.from_config(
        {"root": "out/ds", "vcodec": "h264"}, ObserverContext.of_deployment(_deployment(), robot, tmp_path)
    )
    root = tmp_path / "out" / "ds"
    try:
        assert not root.exists()  # what openral validate builds leaves nothing behind
        sink = recorder.sink
        assert (sink.root, sink.fps, sink.robot_type, sink.vcodec) == (root, 30, robot.robot_id, "h264")
        assert sink.joint_names == recorder.joint_names == robot.joint_names
        assert sink.cameras == [schema.CameraSpec("front", W, H), schema.CameraSpec("wrist", 0, 0)]
        assert not sink.is_open
        recorder.start()
        recorder.start()  # idempotent
        assert sink.is_open
        assert root.is_dir()
    finally:
        recorder.close()
    assert list(root.rglob("*")) == []  # opened and closed without an episode: an empty folder


def test_a_recorder_never_started_touches_no_file_when_closed(tmp_path: Path) -> None:
    recorder = RolloutRecorder.from_config(
        {"root": str(tmp_path / "ds")},
        ObserverContext.of_deployment(_deployment(), load_robot_manifest("so101_follower")),
    )
    recorder.close()
    assert not (tmp_path / "ds").exists()


def test_start_refuses_an_existing_dataset_naming_the_parameter(tmp_path: Path) -> None:
    clock = FakeClock()
    runner, _ = _runner(tmp_path, clock)
    runner.activate()
    runner.episode_start("pick")
    runner.run(3)
    runner.episode_end(success=True)
    runner.deactivate()
    recorder = RolloutRecorder.from_config(
        {"root": "ds"}, ObserverContext.of_deployment(_deployment(), load_robot_manifest("so101_follower"), tmp_path)
    )
    try:
        with pytest.raises(ROSConfigError, match=r"observers\[\]\.params\.root: .*already holds") as refused:
            recorder.start()
        assert "resume: true" in str(refused.value)
    finally:
        recorder.close()
    assert check_dataset(tmp_path / "ds").problems == []


@pytest.mark.parametrize(
    ("params", "rate_hz", "named"),
    [
        ({"root": "ds", "fps": 30}, 30.0, r"observers\[\]\.params\.fps"),
        ({"root": "ds", "vcodec": "vp9"}, 30.0, r"observers\[\]\.params\.vcodec"),
        ({}, 30.0, r"observers\[\]\.params\.root"),
        ({"root": "ds"}, 29.97, "rate_hz"),
    ],
    ids=["unknown-key", "bad-codec", "no-root", "fractional-rate"],
)
def test_a_bad_parameter_names_the_field(tmp_path: Path, params: dict[str, object], rate_hz: float, named: str) -> None:
    with pytest.raises(ROSConfigError, match=named):
        RolloutRecorder.from_config(
            params, ObserverContext.of_deployment(_deployment(rate_hz), load_robot_manifest("so101_follower"), tmp_path)
        )
    assert not (tmp_path / "ds").exists()


def test_a_free_running_loop_records_its_own_names_waits_for_its_encoders_and_errors_name_the_option(
    tmp_path: Path,
) -> None:
    simulated = ObserverContext(
        robot_id="reach",
        rate_hz=10.0,
        joint_names=("x", "y"),
        action_names=("dx", "dy"),
        environment_state_names=("target_x", "target_y"),
        cameras=(CameraSize("top", 64, 48),),
        free_running=True,
        option="--dataset-out",
    )
    recorder = RolloutRecorder.from_config({"root": str(tmp_path / "ds")}, simulated)
    try:
        sink = recorder.sink
        assert (sink.robot_type, sink.fps, sink.overflow) == ("reach", 10, OverflowPolicy.WAIT)
        assert (sink.joint_names, sink.action_names) == (["x", "y"], ["dx", "dy"])
        assert sink.environment_state_names == ["target_x", "target_y"]
        assert sink.cameras == [schema.CameraSpec("top", 64, 48)]
    finally:
        recorder.close()
    with pytest.raises(ROSConfigError, match=r"--dataset-out: .*whole frames per second; the tick rate is 12.5 Hz"):
        RolloutRecorder.from_config({"root": str(tmp_path / "ds")}, replace(simulated, rate_hz=12.5))
    on_a_robot = RolloutRecorder.from_config(
        {"root": str(tmp_path / "robot")}, replace(simulated, free_running=False, option=None)
    )
    try:
        assert on_a_robot.sink.overflow is OverflowPolicy.REPEAT, "a robot does not wait: a late frame is repeated"
    finally:
        on_a_robot.close()


def test_the_tick_columns_mirror_tick_result_fields_under_their_published_names() -> None:
    # LeRobot-loadable datasets already carry these column names: derived from the table, never renamed.
    assert [(c.tick_field, c.column) for c in schema.TICK_COLUMNS] == [
        ("tick_idx", "openral.tick_idx"),
        ("start_ns", "openral.tick_start_ns"),
        ("lateness_ms", "openral.lateness_ms"),
        ("action_applied", "openral.action_applied"),
        ("withheld_reason", "openral.withheld_reason"),
        ("requested_action", "openral.requested_action"),
    ]
    assert {c.tick_field for c in schema.TICK_COLUMNS} <= set(TickResult.model_fields)


def test_a_row_holds_each_mirrored_field_of_its_tick(tmp_path: Path) -> None:
    sink = LeRobotDatasetSink(tmp_path / "ds", fps=FPS, robot_type="arm", joint_names=JOINTS, vcodec="h264")
    recorder = RolloutRecorder(sink, joint_names=JOINTS)
    joints = JointState(names=JOINTS, positions=[0.0, 0.1, 0.2], stamp_ns=1)
    ticks = [
        TickResult(tick_idx=7, start_ns=70, lateness_ms=1.5, step_idx=0, withheld_reason="deadline"),
        TickResult(tick_idx=8, start_ns=80, action_applied=True, requested_action=[1.0, 2.0, 3.0], step_idx=1),
    ]
    recorder.on_episode_start(0, "pick")
    for tick in ticks:
        recorder.on_tick(tick, WorldState(stamp_ns=1, joint_state=joints))
    recorder.on_episode_end(0, success=True)
    recorder.close()
    assert recorder.errors == 0
    rows = pq.read_table(layout.data_file(tmp_path / "ds", 0)).to_pydict()
    for column in schema.TICK_COLUMNS:
        recorded = rows[column.column]
        expected = [tick.model_dump(mode="json")[column.tick_field] for tick in ticks]
        if column.tick_field == "withheld_reason":
            expected = [value or "" for value in expected]
        if column.tick_field == "requested_action":
            assert all(math.isnan(v) for v in recorded[0])
            recorded, expected = recorded[1:], expected[1:]
        assert recorded == expected, column.column  # values exact in float32
