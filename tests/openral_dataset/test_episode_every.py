"""Continuous recording: a runner's episode cut into parts of N seconds, each committed as it fills."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import av
import pyarrow.parquet as pq
import pytest

from openral_core import (
    FrameEncoding,
    ObserverContext,
    RobotEnvironment,
    ROSConfigError,
    SensorFrame,
    SensorReaderConfig,
)
from openral_dataset import layout, schema
from openral_dataset.check import check_dataset
from openral_dataset.recorder import RolloutRecorder
from openral_dataset.testing import numbered_pixels, read_number
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
EVERY_S = 0.5
PART = 15  # EVERY_S x FPS rows


class NumberedReader:
    """A camera whose n-th capture shows the number n."""

    def __init__(self, sensor_id: str, clock: FakeClock) -> None:
        self.sensor_id = sensor_id
        self.clock = clock
        self.seq = 0
        self.is_open = False

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

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


def _runner(root: Path, *, resume: bool = False) -> tuple[HardwareRunner, RolloutRecorder]:
    clock = FakeClock()
    sink = LeRobotDatasetSink(
        root,
        fps=FPS,
        robot_type="so101_follower",
        joint_names=JOINTS,
        cameras=[schema.CameraSpec("front", W, H)],
        vcodec="h264",
        resume=resume,
    )
    recorder = RolloutRecorder(sink, joint_names=JOINTS, episode_every_s=EVERY_S)
    skill = ScriptedSkill(JOINTS, actions=[[0.01 * i, 0.0, 0.0] for i in range(1, 400)])
    skill.configure()
    skill.activate()
    runner = HardwareRunner(
        hal=RecordingHAL(JOINTS, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(sensors=[SensorReaderConfig(sensor_id="front")], clock=clock.now_ns),
        sensor_readers=[NumberedReader("front", clock)],
        rate_hz=FPS,
        clock=clock,
        thumbnail_hz=0.0,
        recorder=recorder,
    )
    return runner, recorder


def _table(root: Path, episode: int) -> dict[str, list[object]]:
    return pq.read_table(layout.data_file(root, episode)).to_pydict()


def _decoded_numbers(root: Path, episode: int) -> list[int]:
    with av.open(str(layout.video_file(root, schema.video_key("front"), episode))) as container:
        return [read_number(f.to_ndarray(format="rgb24")) for f in container.decode(container.streams.video[0])]


def _outcomes(root: Path) -> list[bool | None]:
    lines = (root / layout.OUTCOMES_PATH).read_text().splitlines()
    return [json.loads(line)["success"] for line in lines]


def test_k_times_n_seconds_give_k_episodes_of_n_seconds_while_the_runner_goes_on(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    runner, recorder = _runner(root)
    runner.activate()
    runner.episode_start("pick the cube")
    runner.run(3 * PART)
    runner.episode_end(success=True)
    runner.deactivate()

    assert recorder.errors == 0
    assert [(e.episode_idx, e.frames, e.committed) for e in recorder.episodes] == [(i, PART, True) for i in range(3)]
    report = recorder.report()
    assert (report["episodes_committed"], report["episodes_discarded"], report["frames"]) == (3, 0, 3 * PART)
    checked = check_dataset(root)
    assert checked.problems == []
    assert (checked.episodes, checked.frames, checked.videos) == (3, 3 * PART, 3)
    assert read_tasks(root) == {"pick the cube": 0}
    tables = [_table(root, episode) for episode in range(3)]
    assert [t["index"] for t in tables] == [list(range(i * PART, (i + 1) * PART)) for i in range(3)]
    ticks = [tick for t in tables for tick in t["openral.tick_idx"]]
    assert ticks == list(range(ticks[0], ticks[0] + 3 * PART))  # one run, no tick lost at a cut
    actions = [a[0] for t in tables for a in t["action"]]
    assert actions == pytest.approx([0.01 * i for i in range(1, 3 * PART + 1)], abs=1e-6)  # the skill never reset
    for episode, table in enumerate(tables):
        assert table["frame_index"] == list(range(PART))
        assert table["timestamp"] == pytest.approx([i / FPS for i in range(PART)])
        assert table["episode_index"] == [episode] * PART
        assert _decoded_numbers(root, episode) == table["openral.front.seq"]
    assert _outcomes(root) == [None, None, True]  # a part's outcome is the runner's only for the last


def test_the_runners_episode_end_commits_the_partial_part_and_the_index_stays_contiguous(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    runner, recorder = _runner(root)
    runner.activate()
    runner.episode_start("pick")
    runner.run(PART + 5)
    runner.episode_end(success=False)
    runner.episode_start("place")
    runner.run(7)
    runner.episode_end(success=True)
    runner.episode_start("pick")
    runner.run(PART + 4)
    runner.episode_end(success=True, keep=False)  # a discarded take: only its part under way is lost
    runner.deactivate()

    assert [(e.frames, e.task, e.committed) for e in recorder.episodes] == [
        (PART, "pick", True),
        (5, "pick", True),
        (7, "place", True),
        (PART, "pick", True),
        (4, "pick", False),
    ]
    checked = check_dataset(root)
    assert checked.problems == []
    assert (checked.episodes, checked.frames) == (4, 2 * PART + 12)
    assert [_table(root, e)["episode_index"][0] for e in range(4)] == [0, 1, 2, 3]
    assert _outcomes(root) == [None, False, True, None]
    assert not (root / layout.STAGING_DIR).exists()


_CHILD = textwrap.dedent(
    """
    import sys
    import time
    from pathlib import Path

    from openral_core import FrameEncoding, JointState, SensorFrame, TickResult, WorldState
    from openral_dataset import schema
    from openral_dataset.recorder import RolloutRecorder
    from openral_dataset.testing import numbered_pixels
    from openral_dataset.writer import LeRobotDatasetSink

    root, parts, extra = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    joints = ["j0", "j1", "j2"]
    sink = LeRobotDatasetSink(root, fps=30, robot_type="arm", joint_names=joints,
                              cameras=[schema.CameraSpec("front", 64, 48)], vcodec="h264")
    recorder = RolloutRecorder(sink, joint_names=joints, episode_every_s=0.5)
    recorder.on_episode_start(0, "pick")
    for i in range(parts * 15 + extra):
        stamp = (i + 1) * 33_333_333
        frame = SensorFrame(sensor_id="front", stamp_ns=stamp, width=64, height=48, seq=i,
                            encoding=FrameEncoding.RGB8, data=numbered_pixels(i, 64, 48))
        world = WorldState(stamp_ns=stamp, joint_state=JointState(names=joints, positions=[i, 0, 0], stamp_ns=stamp),
                           image_frames={"front": frame})
        recorder.on_tick(TickResult(tick_idx=i, start_ns=stamp, step_idx=i), world)
        recorder.wait_for_room()
    deadline = time.monotonic() + 60
    while (len(recorder.episodes) < parts or recorder.handled < parts * 15 + extra) and time.monotonic() < deadline:
        time.sleep(0.005)
    print(f"ready {len(recorder.episodes)} {recorder.handled}", flush=True)
    sys.stdin.read()  # killed here, with a part under way
    """
)


@pytest.mark.slow
def test_a_kill_9_mid_run_leaves_exactly_the_finished_parts_and_a_resumable_dataset(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    script = tmp_path / "child.py"
    script.write_text(_CHILD)
    errors = tmp_path / "child.err"  # also where the child's shared-memory tracker reports what it cleans up
    with errors.open("w") as stderr:
        child = subprocess.Popen(
            [sys.executable, str(script), str(root), "3", "7"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
        )
    try:
        assert child.stdout is not None
        lines = iter(child.stdout.readline, "")
        ready = next((line.split() for line in lines if line.startswith("ready")), None)  # logs come first
        assert ready == ["ready", "3", str(3 * PART + 7)], errors.read_text()
        assert (root / layout.STAGING_DIR).is_dir()  # the fourth part is under way
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(30)
        if child.stdin is not None:
            child.stdin.close()
        if child.stdout is not None:
            child.stdout.close()
    assert child.returncode == -signal.SIGKILL

    checked = check_dataset(root)
    assert checked.problems == []
    assert (checked.episodes, checked.frames) == (3, 3 * PART)
    assert checked.notes  # the staging area of the part that was under way: LeRobot never reads it
    assert [_table(root, e)["openral.tick_idx"][0] for e in range(3)] == [0, PART, 2 * PART]

    runner, recorder = _runner(root, resume=True)  # resuming clears what the kill left and goes on
    runner.activate()
    runner.episode_start("pick")
    runner.run(PART)
    runner.episode_end(success=True)
    runner.deactivate()
    assert recorder.errors == 0
    checked = check_dataset(root)
    assert checked.problems == []
    assert checked.notes == []
    assert (checked.episodes, checked.frames) == (4, 4 * PART)
    assert _table(root, 3)["index"] == list(range(3 * PART, 4 * PART))


def test_lerobot_loads_a_continuous_recording(tmp_path: Path) -> None:
    pytest.importorskip(
        "lerobot", reason="needs the 'lerobot' extra, which installs on Python 3.12 or newer (lerobot 0.6)"
    )
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: PLC0415

    root = tmp_path / "ds"
    runner, _ = _runner(root)
    runner.activate()
    runner.episode_start("pick")
    runner.run(2 * PART + 3)
    runner.episode_end(success=True)
    runner.deactivate()
    dataset = LeRobotDataset("local/continuous", root=root)
    assert dataset.num_episodes == 3
    assert len(dataset) == 2 * PART + 3
    item = dataset[PART]  # the first row of the second part
    assert int(item["episode_index"]) == 1
    assert int(item["frame_index"]) == 0
    assert tuple(item["observation.images.front"].shape) == (3, H, W)


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


def test_from_config_takes_episode_every_s(tmp_path: Path) -> None:
    recorder = RolloutRecorder.from_config(
        {"root": "ds", "episode_every_s": 2.5},
        ObserverContext.of_deployment(_deployment(), load_robot_manifest("so101_follower"), tmp_path),
    )
    try:
        assert recorder.part_rows == 75
        assert recorder.highlight is None
    finally:
        recorder.close()


@pytest.mark.parametrize("value", [0, -1.0, float("inf"), float("nan"), "10", True])
def test_a_bad_episode_every_s_names_the_field(tmp_path: Path, value: object) -> None:
    with pytest.raises(ROSConfigError, match=r"observers\[\]\.params\.episode_every_s"):
        RolloutRecorder.from_config(
            {"root": "ds", "episode_every_s": value},
            ObserverContext.of_deployment(_deployment(), load_robot_manifest("so101_follower"), tmp_path),
        )
    assert not (tmp_path / "ds").exists()


@pytest.mark.parametrize("value", [0.0, -2.0, float("nan"), float("inf"), 0.001])
def test_the_recorder_refuses_a_bad_episode_every_s_naming_it(tmp_path: Path, value: float) -> None:
    sink = LeRobotDatasetSink(tmp_path / "ds", fps=FPS, robot_type="arm", joint_names=JOINTS, defer_open=True)
    with pytest.raises(ROSConfigError, match="episode_every_s") as refused:
        RolloutRecorder(sink, joint_names=JOINTS, episode_every_s=value)
    assert refused.value.field == "episode_every_s"
