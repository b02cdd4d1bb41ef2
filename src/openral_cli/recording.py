"""The CLI's recording glue: a deployment's recorder, and ``openral dataset check``.

``openral_dataset`` imports pyarrow and PyAV (the ``dataset`` extra); it is loaded only when a
command asks for a recording.
"""

from __future__ import annotations

import importlib
import math
from pathlib import Path
from typing import Any

import click
from PIL import Image

from openral_cli.errors import exit_codes
from openral_core import ObserverConfig, RobotEnvironment, ROSConfigError, SimEnvironment
from openral_core.environment import THUMBNAILS_OBSERVER
from openral_hal.manifests import load_robot_manifest

MCAP_OPTION = click.option(
    "--mcap",
    "rosbag",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="Also write the session as a ROS 2 bag (MCAP, profile ros2): joint states, commands, images, ticks.",
)
VCODEC_OPTION = click.option(
    "--vcodec",
    type=click.Choice(["libsvtav1", "h264"]),
    default="libsvtav1",
    show_default=True,
    help="Video codec of the recorded cameras.",
)


def build_recorder(env: RobotEnvironment, dataset_out: Path, *, resume: bool, vcodec: str) -> Any:
    """A ``RolloutRecorder`` writing ``env``'s robot and cameras to ``dataset_out`` at the tick rate.

    Raises:
        ROSConfigError: The tick rate is not a whole number (a dataset's fps is), or the dataset
            cannot be opened as asked.
        ROSDependencyMissing: The ``dataset`` extra is not installed.
    """
    if not math.isclose(env.rate_hz, round(env.rate_hz)):
        raise ROSConfigError(
            f"a dataset records whole frames per second; the tick rate is {env.rate_hz:g} Hz",
            field="rate_hz",
            hint="use a whole number of Hz to record",
        )
    writer = importlib.import_module("openral_dataset.writer")
    recorder_module = importlib.import_module("openral_dataset.recorder")
    schema = importlib.import_module("openral_dataset.schema")
    robot = load_robot_manifest(env.hal.robot_id)
    cameras = [schema.CameraSpec(s.sensor_id, s.width or 0, s.height or 0) for s in env.sensors]
    sink = writer.LeRobotDatasetSink(
        dataset_out,
        fps=round(env.rate_hz),
        robot_type=robot.robot_id,
        joint_names=robot.joint_names,
        cameras=cameras,
        vcodec=vcodec,
        resume=resume,
    )
    return recorder_module.RolloutRecorder(sink, joint_names=robot.joint_names)


def build_sim_recorder(scene: SimEnvironment, spec: Any, dataset_out: Path, *, resume: bool, vcodec: str) -> Any:
    """A ``RolloutRecorder`` for simulated episodes: the env's state and action names, its object state, the cameras.

    Raises:
        ROSConfigError: The env's control rate is not a whole number, or the dataset cannot be opened.
        ROSDependencyMissing: The ``dataset`` extra is not installed.
    """
    if not math.isclose(spec.control_hz, round(spec.control_hz)):
        raise ROSConfigError(
            f"a dataset records whole frames per second; {scene.env} steps at {spec.control_hz:g} Hz",
            field="--dataset-out",
        )
    writer = importlib.import_module("openral_dataset.writer")
    recorder_module = importlib.import_module("openral_dataset.recorder")
    schema = importlib.import_module("openral_dataset.schema")
    video = importlib.import_module("openral_dataset.video")
    sink = writer.LeRobotDatasetSink(
        dataset_out,
        fps=round(spec.control_hz),
        robot_type=scene.robot or scene.env_id or scene.env,
        joint_names=list(spec.state_names),
        action_names=list(spec.action_names),
        environment_state_names=list(spec.environment_state_names),
        cameras=[schema.CameraSpec(c.name, c.width, c.height) for c in scene.cameras],
        vcodec=vcodec,
        overflow=video.OverflowPolicy.WAIT,  # a simulation waits for its encoders: no frame is repeated
        resume=resume,
    )
    return recorder_module.RolloutRecorder(sink, joint_names=list(spec.state_names))


def build_rosbag(env: RobotEnvironment, path: Path, *, deployment: Path | None) -> Any:
    """A ``Ros2BagWriter`` for ``env``'s robot into ``path``, with the deployment file attached.

    Raises:
        ROSConfigError: The file exists or cannot be created.
        ROSDependencyMissing: The ``dataset`` extra is not installed.
    """
    bag = importlib.import_module("openral_dataset.ros2_bag")
    robot = load_robot_manifest(env.hal.robot_id)
    return bag.Ros2BagWriter(path, joint_names=robot.joint_names, deployment=deployment)


def with_thumbnails(env: RobotEnvironment, rate_hz: float = 10.0) -> RobotEnvironment:
    """``env`` with the ``thumbnails`` observer (at ``rate_hz`` when it has none): what views and bags show."""
    if any(o.id == THUMBNAILS_OBSERVER for o in env.observers):
        return env
    entry = ObserverConfig(id=THUMBNAILS_OBSERVER, params={"rate_hz": rate_hz})
    return env.model_copy(update={"observers": [*env.observers, entry]})


def recording_summary(recorder: Any) -> str:
    """One line: episodes committed, frames, repeated frames and dropped ticks, and why recording stopped early."""
    committed = [e for e in recorder.episodes if e.committed]
    frames = sum(e.frames for e in committed)
    line = (
        f"dataset {recorder.sink.root}: {len(committed)} episode(s) committed, {frames} frames, "
        f"{recorder.repeated_frames} repeated frame(s), {recorder.dropped_ticks} dropped tick(s)"
    )
    if recorder.failure is not None:
        line += f"; recording stopped early: {recorder.failure}"
    return line


@click.group()
def dataset() -> None:
    """Check and inspect recorded datasets."""


@dataset.command("check")
@click.argument("root", metavar="DIR", type=click.Path(path_type=Path, file_okay=False))
@click.option("--no-video", is_flag=True, help="Skip decoding the videos (faster; checks the tables only).")
def check(root: Path, no_video: bool) -> None:
    """Validate a LeRobotDataset v3.0: layout, counters, index, frame grid, videos, orphans."""
    checker = importlib.import_module("openral_dataset.check")
    report = checker.check_dataset(root, decode_videos=not no_video)
    for note in report.notes:
        click.echo(f"note: {note}", err=True)
    for problem in report.problems:
        click.echo(f"problem: {problem}", err=True)
    if report.problems:
        click.echo(f"{root}: {len(report.problems)} problem(s)", err=True)
        raise SystemExit(1)
    click.echo(
        f"ok: {root} — {report.episodes} episode(s), {report.frames} frames, {report.videos} video file(s) checked"
    )


@click.command()
@click.option("--frame", "frame_path", required=True, metavar="DIR/EPISODE/FRAME", help="The row to show.")
@click.option(
    "--out",
    type=click.Path(path_type=Path, file_okay=False),
    default=Path(),
    show_default=True,
    help="Where the camera frames are written (PNG).",
)
@click.pass_context
def replay(ctx: click.Context, frame_path: str, out: Path) -> None:
    """Show one recorded row: its tick (state, actions, timings, stamps, trace id) and its camera frames."""
    with exit_codes(bool(ctx.obj["debug"])):
        lookup = importlib.import_module("openral_dataset.replay")
        root, episode, frame = lookup.parse_frame_path(frame_path)
        found = lookup.lookup_frame(root, episode, frame)
        for name, value in found.row.items():
            click.echo(f"{name:<32} {_show(value)}")
        out.mkdir(parents=True, exist_ok=True)
        for camera, pixels in found.images.items():
            target = out / f"{camera}_episode{episode}_frame{frame}.png"
            Image.fromarray(pixels).save(target)
            click.echo(f"{'image ' + camera:<32} {target}")


def _show(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    return str(value)
