"""The CLI's recording glue: the observer entries its flags stand for (deployments and scenes), ``openral dataset``.

``openral_dataset`` imports pyarrow and PyAV (the ``dataset`` extra); it is loaded only when a
command asks for a recording.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click
from PIL import Image

from openral_cli.errors import exit_codes
from openral_core import ObserverConfig
from openral_core.environment import THUMBNAILS_OBSERVER, Watched
from openral_observability.observer import TickObserver

if TYPE_CHECKING:
    from openral_dataset.recorder import RolloutRecorder

WatchedT = TypeVar("WatchedT", bound=Watched)
"""A deployment or a scene: anything with an ``observers:`` block."""

FOXGLOVE_DEFAULT_PORT = 8765
FOXGLOVE_IMAGE_HZ = 10.0
"""Camera thumbnails per second for the Foxglove view and bags when the file sets no ``thumbnail_hz``."""

MCAP_OPTION = click.option(
    "--mcap",
    "rosbag",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="Also write the session as a ROS 2 bag (MCAP, profile ros2): joint states, commands, images, ticks.",
)
FOXGLOVE_OPTION = click.option(
    "--foxglove",
    "foxglove_port",
    type=click.IntRange(0, 65535),
    is_flag=False,
    flag_value=FOXGLOVE_DEFAULT_PORT,
    default=None,
    metavar="[PORT]",
    help=f"Serve a live Foxglove WebSocket (joint states, cameras, tick timings, safety events); "
    f"default port {FOXGLOVE_DEFAULT_PORT}.",
)
VCODEC_OPTION = click.option(
    "--vcodec",
    type=click.Choice(["libsvtav1", "h264"]),
    default="libsvtav1",
    show_default=True,
    help="Video codec of the recorded cameras.",
)


def dataset_entry(
    root: Path,
    *,
    resume: bool,
    vcodec: str,
    episode_every_s: float | None = None,
    highlight_s: float | None = None,
) -> ObserverConfig:
    """The ``lerobot_dataset`` observer entry ``--dataset-out`` stands for (the path taken from the working folder)."""
    params: dict[str, Any] = {"root": str(root.expanduser().absolute()), "resume": resume, "vcodec": vcodec}
    if episode_every_s is not None:
        params["episode_every_s"] = episode_every_s
    if highlight_s is not None:
        params["highlight_s"] = highlight_s
    return ObserverConfig.shorthand("lerobot_dataset", params, option="--dataset-out")


def rosbag_entry(path: Path, *, deployment: Path | None) -> ObserverConfig:
    """The ``ros2_bag`` observer entry ``--mcap`` stands for, with the deployment file attached."""
    params: dict[str, Any] = {"path": str(path.expanduser().absolute())}
    if deployment is not None:
        params["attach"] = str(deployment.absolute())
    return ObserverConfig.shorthand("ros2_bag", params, option="--mcap")


def foxglove_entry(port: int) -> ObserverConfig:
    """The ``foxglove`` observer entry ``--foxglove PORT`` stands for."""
    return ObserverConfig.shorthand("foxglove", {"port": port}, option="--foxglove")


def with_observers(env: WatchedT, *entries: ObserverConfig, first: bool = False) -> WatchedT:
    """``env`` (a deployment or a scene) with ``entries`` added to its ``observers:`` (first: before its own)."""
    observers = [*entries, *env.observers] if first else [*env.observers, *entries]
    return env.model_copy(update={"observers": observers})


def with_thumbnails(env: WatchedT, rate_hz: float = 10.0) -> WatchedT:
    """``env`` with the ``thumbnails`` observer (at ``rate_hz`` when it has none): what views and bags show."""
    if any(o.id == THUMBNAILS_OBSERVER for o in env.observers):
        return env
    return with_observers(env, ObserverConfig(id=THUMBNAILS_OBSERVER, params={"rate_hz": rate_hz}))


def with_viewers(
    env: WatchedT, *, rosbag: Path | None, foxglove_port: int | None, config_path: Path | None
) -> WatchedT:
    """``env`` with the entries ``--mcap`` (the file attached) and ``--foxglove`` stand for, and thumbnails for them."""
    if rosbag is not None:
        env = with_observers(with_thumbnails(env, FOXGLOVE_IMAGE_HZ), rosbag_entry(rosbag, deployment=config_path))
    if foxglove_port is not None:
        env = with_observers(with_thumbnails(env, FOXGLOVE_IMAGE_HZ), foxglove_entry(foxglove_port))
    return env


def recorder_of(observers: Sequence[TickObserver]) -> RolloutRecorder:
    """The dataset recorder a ``--dataset-out`` entry added to a runner's observers."""
    from openral_dataset.recorder import RolloutRecorder  # noqa: PLC0415 (the 'dataset' extra, loaded when recording)

    return next(o for o in observers if isinstance(o, RolloutRecorder))


def print_foxglove(observers: Sequence[TickObserver]) -> None:
    """Where the live Foxglove view is served (bound when the runner started it)."""
    from openral_runner.bridges.foxglove import FoxgloveSink  # noqa: PLC0415 (the 'foxglove' extra)

    for sink in observers:
        if isinstance(sink, FoxgloveSink) and sink.port is not None:
            click.echo(f"foxglove: ws://127.0.0.1:{sink.port}  (open {sink.app_url})", err=True)


def recording_summary(recorder: RolloutRecorder) -> str:
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
    from openral_dataset import check as checker  # noqa: PLC0415 (the 'dataset' extra)

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
        from openral_dataset import replay as lookup  # noqa: PLC0415 (the 'dataset' extra)

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
