"""``openral record``: LeRobot's recording workflow on openral's loop.

Episodes of ``--episode-time-s`` are recorded one after another, with ``--reset-time-s`` between
them during which the robot holds and nothing is recorded. Keys (``n``/→ next, ``r``/← re-record,
``q``/Esc stop) work in any terminal. A re-recorded take is discarded without a trace. On SIGINT
or SIGTERM the episode under way is kept or discarded (``--on-stop``), the dataset finalized, and
the command exits 130/143. When the dataset cannot be written (a full or read-only disk), recording
stops at once, the committed episodes stay intact, and the command exits 1 with one line.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
import structlog

from openral_cli.command_lifecycle import STOP_EXIT_CODES, command_span, running
from openral_cli.console import CONSOLE_OPTION, ConsoleAddress, attach_console, with_console
from openral_cli.controls import RunControls, run_controls, takeover_keys
from openral_cli.errors import EXIT_OK, EXIT_RUNTIME, exit_codes
from openral_cli.keys import KeyCommand, KeyReader
from openral_cli.options import Seconds
from openral_cli.recording import (
    MCAP_OPTION,
    VCODEC_OPTION,
    dataset_entry,
    recorder_of,
    rosbag_entry,
    with_observers,
    with_thumbnails,
)
from openral_cli.signals import StopSignals
from openral_cli.status import LiveStatus
from openral_core import RobotEnvironment, ROSRuntimeError, ROSStopRequested, StopReason
from openral_runner.hardware import HardwareRunner

if TYPE_CHECKING:
    from openral_dataset.recorder import RolloutRecorder

_log = structlog.get_logger("openral")

_FAILED_STOPS = frozenset({StopReason.FAULTS, StopReason.ESTOP, StopReason.DEADLINE})


@dataclass
class _Keys:
    """The last key command, and an event the reset wait wakes on."""

    recording: HardwareRunner | None = None
    """The runner while an episode records: a key ends its run."""
    pending: KeyCommand | None = None
    pressed: threading.Event = field(default_factory=threading.Event)
    controls: RunControls = field(default_factory=RunControls)
    """What a key does beside the recording keys (take over): it never ends the episode."""

    def __call__(self, command: KeyCommand) -> None:
        if self.controls.offers(command):
            self.controls(command)
            return
        self.pending = command
        self.pressed.set()
        runner = self.recording
        if runner is not None:
            runner.request_stop()  # ends the episode's run(); the loop reads which key it was

    def take(self) -> KeyCommand | None:
        command, self.pending = self.pending, None
        self.pressed.clear()
        return command


@dataclass
class _Totals:
    committed: int = 0
    discarded: int = 0
    frames: int = 0
    recorded_s: float = 0.0
    missed_slots: int = 0
    stop: StopReason | None = None


@click.command()
@click.option("--config", "config_path", required=True, type=click.Path(path_type=Path), help="Deployment file.")
@click.option("--dataset-out", required=True, type=click.Path(path_type=Path, file_okay=False), help="Dataset folder.")
@click.option("--episodes", type=click.IntRange(min=1), default=1, show_default=True, help="Episodes to record.")
@click.option("--episode-time-s", type=Seconds(), default=20.0, show_default=True, help="Length of each episode.")
@click.option(
    "--reset-time-s",
    type=Seconds(zero_ok=True),
    default=5.0,
    show_default=True,
    help="Pause between episodes: the robot holds, nothing is recorded.",
)
@click.option("--task", "tasks", multiple=True, help="Task string; repeat it to cycle tasks over the episodes.")
@click.option("--resume", is_flag=True, help="Add episodes to the dataset already in --dataset-out.")
@VCODEC_OPTION
@click.option(
    "--on-stop",
    type=click.Choice(["keep", "discard"]),
    default="keep",
    show_default=True,
    help="What a stop signal does to the episode under way.",
)
@MCAP_OPTION
@CONSOLE_OPTION
@click.option("--otlp-endpoint", metavar="URL", default=None, help="Export telemetry over OTLP to this collector.")
@click.pass_context
def record(
    ctx: click.Context,
    *,
    config_path: Path,
    dataset_out: Path,
    episodes: int,
    episode_time_s: float,
    reset_time_s: float,
    tasks: tuple[str, ...],
    resume: bool,
    vcodec: str,
    on_stop: str,
    rosbag: Path | None,
    console: ConsoleAddress | None,
    otlp_endpoint: str | None,
) -> None:
    """Record episodes into a LeRobotDataset v3.0 (keys: n/→ next, r/← re-record, q/Esc stop)."""
    with StopSignals() as signals, exit_codes(bool(ctx.obj["debug"])):
        with command_span(
            "record", config_path, otlp_endpoint=otlp_endpoint, otlp_protocol=None, trace_sample_ratio=None
        ):
            env = RobotEnvironment.from_yaml(config_path, field="--config")
            task_list = list(tasks) or [env.task.instruction or ""]
            env = with_observers(env, dataset_entry(dataset_out, resume=resume, vcodec=vcodec), first=True)
            if rosbag is not None:
                env = with_observers(with_thumbnails(env), rosbag_entry(rosbag, deployment=config_path))
            env = with_console(env, console)
            keys = _Keys()
            totals = _Totals()
            recorder: RolloutRecorder | None = None
            try:
                key_reader = KeyReader(keys, extra=takeover_keys(env))
                with key_reader, running(env, config_path.parent, signals=signals) as runner:
                    recorder = recorder_of(runner.observers)
                    recorder.on_failure = runner.request_stop  # a write failure ends the episode under way
                    keys.controls = run_controls(env, runner)
                    # The console's buttons are the keys: the same path, the same effect.
                    attach_console(
                        runner,
                        next=lambda: keys(KeyCommand.NEXT),
                        rerecord=lambda: keys(KeyCommand.RERECORD),
                        stop=lambda: keys(KeyCommand.STOP),
                        **keys.controls.buttons,
                    )
                    _record_episodes(
                        runner,
                        recorder,
                        keys,
                        totals,
                        episodes=episodes,
                        episode_time_s=episode_time_s,
                        reset_time_s=reset_time_s,
                        tasks=task_list,
                        keep_on_stop=on_stop == "keep",
                        title=env.name,
                    )
            except ROSStopRequested as exc:
                totals.stop = StopReason(exc.reason)
        if recorder is not None:  # None: stopped while starting, before the dataset was opened
            _print_summary(totals, recorder)
            if recorder.failure is not None:
                raise ROSRuntimeError(str(recorder.failure))
        code = EXIT_OK if totals.stop is None else STOP_EXIT_CODES.get(totals.stop, EXIT_OK)
        if recorder is not None and recorder.errors:
            code = EXIT_RUNTIME
    raise SystemExit(code)


def _record_episodes(
    runner: HardwareRunner,
    recorder: RolloutRecorder,
    keys: _Keys,
    totals: _Totals,
    *,
    episodes: int,
    episode_time_s: float,
    reset_time_s: float,
    tasks: list[str],
    keep_on_stop: bool,
    title: str,
) -> None:
    take = 0
    while totals.committed < episodes and recorder.failure is None:
        task = tasks[totals.committed % len(tasks)]
        if keys.take() is KeyCommand.STOP:  # pressed while the last episode was committed
            return
        runner.episode_start(task)
        click.echo(f"episode {totals.committed + 1}/{episodes} (take {take + 1}): {task!r}", err=True)
        keys.recording = runner
        try:
            with LiveStatus(runner, sys.stderr, title=f"{title} — recording"):
                result = runner.run(duration_s=episode_time_s)
        finally:
            keys.recording = None
        command = keys.take()
        if recorder.failure is not None:  # it stopped the run: nothing more can be written
            runner.episode_end(success=False, keep=False)
            _count(totals, result, kept=False)
            return
        signalled = result.stop_reason not in (StopReason.DURATION, StopReason.STOP_REQUESTED, StopReason.SKILL_DONE)
        if signalled:
            failed = result.stop_reason in _FAILED_STOPS
            keep = keep_on_stop and not failed
            runner.episode_end(success=False, keep=keep)
            _count(totals, result, kept=keep)
            totals.stop = result.stop_reason
            _log.error("recording stopped", reason=str(result.stop_reason), episode_kept=keep)
            return
        if command is KeyCommand.RERECORD:
            runner.episode_end(success=False, keep=False)
            _count(totals, result, kept=False)
            take += 1
            click.echo("re-recording: that take was discarded", err=True)
        else:
            runner.episode_end(success=True)
            _count(totals, result, kept=True)
            take = 0
            if command is KeyCommand.STOP:
                return
        if totals.committed < episodes and _reset(runner, keys, reset_time_s) is KeyCommand.STOP:
            return
        recorder.wait_for_commit()  # committed during the reset; a write failure stops before the next episode
        if recorder.failure is not None:
            _uncount_failed(totals, recorder)
            return


def _reset(runner: HardwareRunner, keys: _Keys, reset_time_s: float) -> KeyCommand | None:
    """Hold the robot for the reset (nothing ticks, nothing is recorded); ``n`` ends it early.

    A stop signal during the reset ends it too: the next ``run()`` then returns at once.
    """
    if reset_time_s <= 0:
        return None
    click.echo(f"reset: {reset_time_s:g} s (n: start the next episode now, q: stop)", err=True)
    deadline = time.monotonic() + reset_time_s
    while (left := deadline - time.monotonic()) > 0 and runner.stop_requested is None:
        if keys.pressed.wait(min(left, 0.1)):
            command = keys.take()
            if command in (KeyCommand.NEXT, KeyCommand.STOP):
                return command
    return None


def _uncount_failed(totals: _Totals, recorder: Any) -> None:
    """The episode whose commit failed was counted as kept: count it as discarded."""
    committed = sum(1 for e in recorder.episodes if e.committed)
    totals.discarded += totals.committed - committed
    totals.committed = committed


def _count(totals: _Totals, result: Any, *, kept: bool) -> None:
    if kept:
        totals.committed += 1
        totals.frames += result.n_ticks
        totals.recorded_s += result.duration_s
    else:
        totals.discarded += 1
    totals.missed_slots += result.missed_slots


def _print_summary(totals: _Totals, recorder: RolloutRecorder) -> None:
    committed = [e for e in recorder.episodes if e.committed]
    frames = sum(e.frames for e in committed)
    fps = frames / totals.recorded_s if totals.recorded_s > 0 else 0.0
    click.echo(
        f"recorded {len(committed)} episode(s), {frames} frames into {recorder.sink.root} "
        f"(effective {fps:.2f} fps; {totals.discarded} take(s) discarded; "
        f"{recorder.repeated_frames} repeated frame(s), {recorder.dropped_ticks} dropped tick(s), "
        f"{totals.missed_slots} missed slot(s))",
        err=True,
    )
