"""``openral record``: episodes from a real video-file camera and the twin's camera, checked with pyarrow and PyAV only.

The video-file camera plays a test video whose frame ``i`` shows the number ``i`` in large blocks,
so the decoded frame of every row can be compared with the capture sequence the row records.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from openral_cli import record
from openral_cli.main import cli
from openral_dataset import layout, schema
from openral_dataset.check import check_dataset
from openral_dataset.recorder import RolloutRecorder
from openral_dataset.testing import numbered_pixels, read_number
from openral_dataset.writer import LeRobotDatasetSink, read_tasks
from openral_hal.testing import RecordingHAL
from openral_rskill.testing import ScriptedSkill
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import FakeClock
from openral_world_state import WorldStateAggregator

HELLO = Path(__file__).parents[2] / "deployments" / "so101_twin_hello.yaml"

VIDEO_FRAMES = 600
W, H = 320, 240

DEPLOYMENT = """
name: record_test
rate_hz: 30
hal:
  robot_id: so101_follower
  adapter: mujoco_twin
vla:
  id: hello
task:
  instruction: wave hello
sensors:
  - sensor_id: numbered
    backend: opencv_thread
    required: true
    fps: 30
    width: {w}
    height: {h}
    encoding: bgr8
    max_age_ms: 200
    backend_params:
      device: numbered.mp4
      paced: true
{twin_camera}
safety:
  client: envelope
  mode: clamp
"""

TWIN_CAMERA = """
  - sensor_id: front
    backend: mujoco_camera
    required: false
    fps: 15
    width: 160
    height: 120
    encoding: rgb8
    max_age_ms: 500
"""


def _numbered_video(path: Path) -> None:
    """A lossless-enough H.264 file whose frame i shows i."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=30, options={"crf": "10", "g": "30"})
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        stream.codec_context.time_base = Fraction(1, 30)
        for i in range(VIDEO_FRAMES):
            frame = av.VideoFrame.from_ndarray(numbered_pixels(i, W, H), format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


@pytest.fixture
def deployment(tmp_path: Path) -> Callable[..., Path]:
    _numbered_video(tmp_path / "numbered.mp4")

    def write(*, twin_camera: bool) -> Path:
        path = tmp_path / ("with_twin.yaml" if twin_camera else "video_only.yaml")
        path.write_text(DEPLOYMENT.format(w=W, h=H, twin_camera=TWIN_CAMERA if twin_camera else ""))
        return path

    return write


def _decode_numbers(path: Path) -> list[int]:
    with av.open(str(path)) as container:
        return [read_number(f.to_ndarray(format="rgb24")) for f in container.decode(container.streams.video[0])]


def _start(deploy_process, config: Path, out: Path, *args: str):
    """``openral record`` of ``config`` into ``out`` (H.264, no reset pause unless ``args`` say otherwise)."""
    return deploy_process(
        ["record", "--config", str(config), "--dataset-out", str(out), "--vcodec", "h264", "--reset-time-s", "0", *args]
    )


def _record(deploy_process, config: Path, out: Path, *args: str) -> str:
    proc = _start(deploy_process, config, out, *args)
    code, _ = proc.finish(timeout=120)
    assert code == 0, proc.stderr
    return proc.stderr


@pytest.mark.gl
def test_three_episodes_two_tasks_every_row_shows_the_frame_it_records(deploy_process, deployment, tmp_path) -> None:
    config = deployment(twin_camera=True)
    out = tmp_path / "ds"
    _record(
        deploy_process,
        config,
        out,
        "--episodes",
        "2",
        "--episode-time-s",
        "1.0",
        "--task",
        "pick the cube",
        "--task",
        "place the cube",
    )
    stderr = _record(
        deploy_process, config, out, "--resume", "--episodes", "1", "--episode-time-s", "1.6", "--task", "pick the cube"
    )
    assert "recorded 1 episode(s)" in stderr

    report = check_dataset(out)
    assert report.problems == []
    assert report.episodes == 3
    assert read_tasks(out) == {"pick the cube": 0, "place the cube": 1}
    lengths = []
    for episode in range(3):
        table = pq.read_table(layout.data_file(out, episode)).to_pydict()
        lengths.append(len(table["index"]))
        numbers = _decode_numbers(layout.video_file(out, schema.video_key("numbered"), episode))
        assert len(numbers) == len(table["index"])
        seqs = table["openral.numbered.seq"]
        repeated = table["openral.numbered.repeated"]
        for k, (number, seq) in enumerate(zip(numbers, seqs, strict=True)):
            if not repeated[k]:
                assert number == seq % VIDEO_FRAMES, f"episode {episode} row {k}"
        front = av.open(str(layout.video_file(out, schema.video_key("front"), episode)))
        assert front.streams.video[0].frames in (0, len(numbers))  # containers may not count; decode below
        assert sum(1 for _ in front.decode(front.streams.video[0])) == len(numbers)
        front.close()
        assert table["task_index"] == [[0, 1, 0][episode]] * len(numbers)
        assert np.all(np.diff(table["openral.tick_idx"]) >= 1)
    assert len(set(lengths)) >= 2  # 1 s, 1 s and 1.6 s episodes


def test_sigkill_in_episode_two_leaves_episode_one_and_resume_fills_the_gap(
    deploy_process, deployment, tmp_path
) -> None:
    config = deployment(twin_camera=False)
    out = tmp_path / "ds"
    proc = _start(deploy_process, config, out, "--episodes", "3", "--episode-time-s", "1.0")
    proc.wait_for("episode committed")
    proc.wait_for("episode 2/3")
    proc.wait_for("recording episode              episode=1")
    proc.signal_group(signal.SIGKILL)
    proc.proc.wait(10)
    proc.close()

    report = check_dataset(out)
    # Whatever episode 2 had written is staged outside the dataset: a note, not a problem; loading ignores it.
    assert report.problems == []
    assert [n for n in report.notes if n.startswith(layout.STAGING_DIR)]
    assert report.episodes == 1

    _record(deploy_process, config, out, "--resume", "--episodes", "1", "--episode-time-s", "1.0")
    report = check_dataset(out)
    assert report.problems == []
    assert report.episodes == 2
    first = pq.read_table(layout.data_file(out, 0)).column("index").to_pylist()
    second = pq.read_table(layout.data_file(out, 1)).column("index").to_pylist()
    assert second[0] == first[-1] + 1  # no index gap


@pytest.mark.parametrize(("on_stop", "kept"), [("keep", 2), ("discard", 1)])
def test_ctrl_c_keeps_or_discards_the_episode_under_way_and_exits_130(
    deploy_process,
    deployment,
    tmp_path: Path,
    on_stop: str,
    kept: int,
) -> None:
    config = deployment(twin_camera=False)
    out = tmp_path / "ds"
    proc = _start(deploy_process, config, out, "--episodes", "5", "--episode-time-s", "1.0", "--on-stop", on_stop)
    proc.wait_for("episode committed")
    proc.wait_for("recording episode              episode=1")
    proc.signal_group(signal.SIGINT)
    code, _ = proc.finish(timeout=60)
    assert code == 130, proc.stderr
    report = check_dataset(out)
    assert report.problems == []
    assert report.episodes == kept


def test_deploy_records_its_run_as_one_episode_and_reports_it(deploy_process, deployment, tmp_path: Path) -> None:
    import json  # noqa: PLC0415

    config = deployment(twin_camera=False)
    out = tmp_path / "ds"
    proc = deploy_process(
        [
            "deploy",
            "--config",
            str(config),
            "--max-ticks",
            "25",
            "--dataset-out",
            str(out),
            "--task",
            "wave",
            "--vcodec",
            "h264",
            "--json",
        ]
    )
    code, stdout = proc.finish(timeout=120)
    assert code == 0, proc.stderr
    result = json.loads(stdout)
    assert result["metadata"]["recording"] == {
        "episodes_committed": 1,
        "episodes_discarded": 0,
        "frames": 25,
        "repeated_frames": result["metadata"]["recording"]["repeated_frames"],
        "dropped_ticks": 0,
        "errors": 0,
    }
    report = check_dataset(out)
    assert report.problems == []
    assert (report.episodes, report.frames) == (1, 25)
    assert read_tasks(out) == {"wave": 0}


@pytest.mark.parametrize("command", ["record", "deploy"])
@pytest.mark.parametrize("resume", [[], ["--resume"]], ids=["new", "resume"])
def test_a_folder_that_is_not_a_dataset_is_refused_with_exit_2_and_nothing_is_deleted(
    tmp_path: Path, command: str, resume: list[str]
) -> None:
    proj = tmp_path / "proj"
    (proj / "data").mkdir(parents=True)
    (proj / "data" / "measurements.csv").write_text("t,x\n")
    (proj / "videos" / "holiday").mkdir(parents=True)
    (proj / "videos" / "holiday" / "beach.mp4").write_text("x\n")
    ticks = ["--max-ticks", "10"] if command == "deploy" else ["--episodes", "1"]

    result = CliRunner().invoke(cli, [command, "--config", str(HELLO), *ticks, "--dataset-out", str(proj), *resume])
    assert result.exit_code == 2, result.output
    assert "is not an openral dataset" in result.output
    assert "--resume" not in result.output.split("error:")[-1]  # the hint does not invite a clean-up
    assert (proj / "data" / "measurements.csv").read_text() == "t,x\n"
    assert (proj / "videos" / "holiday" / "beach.mp4").read_text() == "x\n"


def test_a_folder_that_cannot_be_written_is_refused_before_the_first_tick(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("")
    out = tmp_path / "a-file" / "ds"
    result = CliRunner().invoke(cli, ["record", "--config", str(HELLO), "--dataset-out", str(out)])
    assert result.exit_code == 2, result.output
    assert f"--dataset-out: cannot write into {out}" in result.output
    assert "recording episode" not in result.output


def test_a_disk_that_fills_after_episode_one_stops_recording_there(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    joints = ["j0", "j1"]
    clock = FakeClock()
    root = tmp_path / "ds"
    sink = LeRobotDatasetSink(root, fps=30, robot_type="arm", joint_names=joints, vcodec="h264")
    begun: list[str] = []
    begin = sink.begin_episode
    monkeypatch.setattr(sink, "begin_episode", lambda task: begun.append(task) or begin(task))
    recorder = RolloutRecorder(sink, joint_names=joints)
    skill = ScriptedSkill(joints, actions=[[0.01 * i, 0.0] for i in range(1, 400)])
    skill.configure()
    skill.activate()
    runner = HardwareRunner(
        hal=RecordingHAL(joints, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(sensors=[], clock=clock.now_ns),
        sensor_readers=[],
        rate_hz=30,
        clock=clock,
        thumbnail_hz=0.0,
        recorder=recorder,
    )
    real_fsync = os.fsync

    def filling(fd: int) -> None:  # the disk is full once the first episode is in
        if (root / layout.INFO_PATH).exists():
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", filling)
    runner.activate()
    recorder.on_failure = runner.request_stop
    totals = record._Totals()
    record._record_episodes(
        runner,
        recorder,
        record._Keys(),
        totals,
        episodes=4,
        episode_time_s=0.2,
        reset_time_s=0.0,
        tasks=["wave"],
        keep_on_stop=True,
        title="test",
    )
    runner.deactivate()
    monkeypatch.undo()

    assert begun == ["wave", "wave"]  # episodes 3 and 4 were never started
    assert (totals.committed, totals.discarded) == (1, 1)
    assert recorder.failure is not None
    assert f"cannot write episode 1 into {root}: No space left on device" in str(recorder.failure)
    report = check_dataset(root)
    assert report.problems == []
    assert report.episodes == 1


def test_a_disk_too_small_for_the_first_episode_exits_1_with_one_line_and_leaves_the_folder_usable(
    tmp_path: Path,
) -> None:

    out = tmp_path / "ds"
    # A real write failure without a full disk: files may not grow past 4 KiB (EFBIG, "File too large").
    args = ["record", "--config", str(HELLO), "--dataset-out", str(out), "--episodes", "3"]
    proc = _openral_with_small_files([*args, "--episode-time-s", "0.5", "--reset-time-s", "0"])
    assert proc.returncode == 1, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    assert f"cannot write episode 0 into {out}: File too large" in errors[0]
    assert "Traceback" not in proc.stderr
    assert "episode 2/3" not in proc.stderr  # recording stopped at the failure
    assert layout.foreign_files(out) == []  # no metadata of an episode that does not exist
    assert not (out / layout.STAGING_DIR).exists()


@pytest.mark.parametrize(
    "command",
    [
        ["deploy", "--config", str(HELLO), "--max-ticks", "60"],
        [
            "sim",
            "run",
            "--config",
            str(HELLO.parents[1] / "scenes" / "sim" / "mock_reach.yaml"),
            "--skill",
            "mock_reach_expert",
            "--n-episodes",
            "3",
            "--no-cameras",
        ],
    ],
    ids=["deploy", "sim-run"],
)
def test_deploy_and_sim_run_exit_1_when_the_dataset_cannot_be_written(tmp_path: Path, command: list[str]) -> None:
    out = tmp_path / "ds"
    proc = _openral_with_small_files([*command, "--dataset-out", str(out)])
    assert proc.returncode == 1, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    assert str(out) in errors[0]
    assert "Traceback" not in proc.stderr
    assert layout.foreign_files(out) == []


def _openral_with_small_files(args: list[str]) -> subprocess.CompletedProcess[str]:
    """``openral ARGS`` in a process whose files may not grow past 4 KiB: a real write failure (EFBIG, "File
    too large") without filling a disk."""
    limited = (
        "import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096)); "
        "from openral_cli.main import main; sys.argv[0] = 'openral'; main()"
    )
    return subprocess.run(
        [sys.executable, "-c", limited, *args],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
