"""The ``openral`` command: YAML in, exit code out."""

from __future__ import annotations

import contextlib
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import click
import structlog

from openral_cli.command_lifecycle import command_span, exit_code, print_result, running, stopped_before_start
from openral_cli.console import CONSOLE_OPTION, ConsoleAddress, attach_console, with_console
from openral_cli.controls import run_controls
from openral_cli.errors import EXIT_CONFIG, EXIT_OK, exit_codes
from openral_cli.keys import KeyCommand, KeyReader
from openral_cli.mujoco_gl import check_mujoco_gl
from openral_cli.options import Seconds
from openral_cli.record import record
from openral_cli.recording import (
    FOXGLOVE_OPTION,
    MCAP_OPTION,
    VCODEC_OPTION,
    dataset,
    dataset_entry,
    print_foxglove,
    recorder_of,
    recording_summary,
    replay,
    with_observers,
    with_viewers,
)
from openral_cli.serve import serve
from openral_cli.signals import StopSignals
from openral_cli.sim import benchmark, sim
from openral_cli.status import LiveStatus
from openral_core import (
    RobotEnvironment,
    ROSConfigError,
    ROSDeadlineMissed,
    ROSRuntimeError,
    ROSStopRequested,
    RunResult,
    StopReason,
)
from openral_core.schema import FILE_MODELS, schema_json
from openral_dataset.highlight import MAX_HIGHLIGHT_S
from openral_hal.manifests import load_robot_manifest
from openral_observability import semconv
from openral_observability.logs import OTelLogBridge, add_trace_ids
from openral_observability.setup import PROTOCOLS
from openral_runner.factory import check_deployment

_SUCCESSFUL_STOPS = frozenset({StopReason.MAX_TICKS, StopReason.DURATION, StopReason.SKILL_DONE})
"""How a recorded run may end and still count as a successful episode."""
_log = structlog.get_logger("openral")


@dataclass(frozen=True)
class Recording:
    """What ``deploy --dataset-out`` records: one episode of the run."""

    root: Path
    task: str
    resume: bool
    vcodec: str
    episode_every_s: float | None = None
    highlight_s: float | None = None


class _Stderr:
    """Whatever ``sys.stderr`` is at the time of each write, so log lines scroll above the live status."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


def _configure_logging(debug: bool) -> None:
    """Logs go to stderr so stdout carries only results (``--json``).

    Each line carries the current trace and span ids when tracing is on, and becomes an
    OpenTelemetry log record too (a no-op until telemetry is set up).
    """
    structlog.configure(
        processors=[
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="%H:%M:%S"),
            add_trace_ids,
            OTelLogBridge(),
            structlog.dev.ConsoleRenderer(colors=sys.stderr.isatty()),
        ],
        wrapper_class=structlog.make_filtering_bound_logger(logging.DEBUG if debug else logging.INFO),
        logger_factory=structlog.PrintLoggerFactory(file=_Stderr()),  # type: ignore[arg-type]
        cache_logger_on_first_use=False,  # so a later configure() (tests, embedding) takes effect everywhere
    )


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--debug", is_flag=True, help="Show tracebacks and debug logs.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """openral: run a robot skill at a steady rate, safely, with every tick traced."""
    ctx.obj = {"debug": debug}
    _configure_logging(debug)
    with exit_codes(debug):  # the environment, resolved here once for every command
        check_mujoco_gl()


@cli.command()
@click.option(
    "--config",
    "config_path",
    required=True,
    type=click.Path(path_type=Path),
    help="Deployment file (RobotEnvironment YAML).",
)
@click.option("--max-ticks", type=click.IntRange(min=0), default=None, help="Stop after this many ticks.")
@click.option("--duration", type=Seconds(), default=None, help="Stop after S seconds (a positive, finite number).")
@click.option("--json", "as_json", is_flag=True, help="Print the RunResult as JSON on stdout, nothing else.")
@click.option(
    "--otlp-endpoint",
    metavar="URL",
    default=None,
    help="Export traces, metrics and logs over OTLP to this collector (default: OTEL_EXPORTER_OTLP_ENDPOINT).",
)
@click.option(
    "--otlp-protocol",
    type=click.Choice(PROTOCOLS),
    default=None,
    help="OTLP transport (default: OTEL_EXPORTER_OTLP_PROTOCOL, else http/protobuf).",
)
@click.option(
    "--trace-sample-ratio",
    type=click.FloatRange(0.0, 1.0),
    default=None,
    help="Fraction of ticks traced, each tick whole (0.1: every tenth tick); default: all.",
)
@FOXGLOVE_OPTION
@CONSOLE_OPTION
@click.option(
    "--dataset-out",
    type=click.Path(path_type=Path, file_okay=False),
    default=None,
    help="Record the run as one episode of a LeRobotDataset v3.0 in this folder.",
)
@click.option("--task", default="", help="The episode's task string (with --dataset-out).")
@MCAP_OPTION
@click.option("--resume", is_flag=True, help="Add the episode to the dataset already in --dataset-out.")
@VCODEC_OPTION
@click.option(
    "--episode-every-s",
    type=Seconds(),
    default=None,
    help="With --dataset-out: commit the run as episodes of this many seconds (a crash loses at most one).",
)
@click.option(
    "--highlight-s",
    type=Seconds(maximum=MAX_HIGHLIGHT_S),
    default=None,
    help="With --dataset-out: keep the last S seconds in memory; the s key or the console's button saves them "
    f"as one episode (nothing else is written). At most {MAX_HIGHLIGHT_S:g} s.",
)
@click.pass_context
def deploy(
    ctx: click.Context,
    *,
    config_path: Path,
    max_ticks: int | None,
    duration: float | None,
    as_json: bool,
    otlp_endpoint: str | None,
    otlp_protocol: str | None,
    trace_sample_ratio: float | None,
    foxglove_port: int | None,
    console: ConsoleAddress | None,
    dataset_out: Path | None,
    task: str,
    rosbag: Path | None,
    resume: bool,
    vcodec: str,
    episode_every_s: float | None,
    highlight_s: float | None,
) -> None:
    """Run a deployment until --max-ticks, --duration, Ctrl-C or a safety stop.

    Every tick is traced under one cli.command span, which continues the trace named by a
    TRACEPARENT environment variable when there is one. Telemetry is exported only when an
    endpoint is given (flag or OTEL_* variables) and is flushed on every exit.

    SIGINT and SIGTERM, however many and whenever they arrive, lead to one orderly stop: the
    tick finishes, the robot holds, everything closes (start-up included), telemetry is flushed
    and the RunResult printed (exit 130 / 143). Two more within a second force torque off and exit.
    """
    debug = bool(ctx.obj["debug"])
    with StopSignals() as signals, exit_codes(debug):
        with command_span(
            "deploy",
            config_path,
            otlp_endpoint=otlp_endpoint,
            otlp_protocol=otlp_protocol,
            trace_sample_ratio=trace_sample_ratio,
        ) as span:
            env = RobotEnvironment.from_yaml(config_path, field="--config")
            if dataset_out is None and (episode_every_s is not None or highlight_s is not None):
                raise ROSConfigError(
                    "records into a dataset", field="--episode-every-s/--highlight-s", hint="add --dataset-out DIR"
                )
            try:
                result = _deploy(
                    env,
                    config_path.parent,
                    max_ticks,
                    duration,
                    signals=signals,
                    quiet=as_json,
                    foxglove_port=foxglove_port,
                    console=console,
                    recording=None
                    if dataset_out is None
                    else Recording(
                        dataset_out, task or env.task.instruction or "", resume, vcodec, episode_every_s, highlight_s
                    ),
                    rosbag=rosbag,
                    config_path=config_path,
                )
            except ROSDeadlineMissed as exc:
                if exc.run_result is not None:
                    print_result(exc.run_result, as_json=as_json, err=not as_json)
                raise
            span.set_attributes(
                {semconv.ATTR_RUN_STOP_REASON: result.stop_reason, semconv.ATTR_RUN_TICKS: result.n_ticks}
            )
        print_result(result, as_json=as_json)
        code = exit_code(result.stop_reason)
    raise SystemExit(code)


def _deploy(
    env: RobotEnvironment,
    base_dir: Path,
    max_ticks: int | None,
    duration: float | None,
    *,
    signals: StopSignals,
    quiet: bool,
    foxglove_port: int | None = None,
    console: ConsoleAddress | None = None,
    recording: Recording | None = None,
    rosbag: Path | None = None,
    config_path: Path | None = None,
) -> RunResult:
    """Build, start, run and close one deployment; a stop signal at any point unwinds what was started.

    ``--dataset-out``, ``--mcap``, ``--foxglove`` and ``--console`` add the observer entries they stand for; the
    runner builds and starts them as it does the file's own.
    """
    if recording is not None:  # first, as a file would list it: it hears each tick before the viewers
        entry = dataset_entry(
            recording.root,
            resume=recording.resume,
            vcodec=recording.vcodec,
            episode_every_s=recording.episode_every_s,
            highlight_s=recording.highlight_s,
        )
        env = with_observers(env, entry, first=True)
    env = with_viewers(env, rosbag=rosbag, foxglove_port=foxglove_port, config_path=config_path)
    env = with_console(env, console)
    recorder = None
    try:
        with running(env, base_dir, signals=signals) as runner:
            if recording is not None:
                recorder = recorder_of(runner.observers)
                recorder.on_failure = runner.request_stop  # the dataset cannot be written: stop there
            if foxglove_port is not None and not quiet:
                print_foxglove(runner.observers)
            controls = run_controls(env, runner, recorder)
            controls.actions[KeyCommand.STOP] = runner.request_stop
            # The console's stop is an orderly stop, as Ctrl-C; its takeover and highlight buttons
            # do what the keys do.
            attach_console(runner, stop=runner.request_stop, **controls.buttons)
            _log.info("running", deployment=env.name, rate_hz=env.rate_hz, skill=env.vla.id, robot=env.hal.robot_id)
            if recording is not None:
                runner.episode_start(recording.task)
            keys = KeyReader(controls, extra=controls.keys) if controls.keys else contextlib.nullcontext()
            with keys, LiveStatus(runner, sys.stderr, title=env.name):
                result = runner.run(max_ticks, duration_s=duration)
            if recording is not None:
                runner.episode_end(success=result.stop_reason in _SUCCESSFUL_STOPS)
        if recorder is not None:  # closed with the runner: every tick is written, the report is final
            result.metadata["recording"] = recorder.report()
    except ROSStopRequested as exc:
        _log.info("stopped before the first tick; everything started was closed", reason=exc.reason)
        return stopped_before_start(env, exc)
    finally:
        if recorder is not None and not quiet:
            click.echo(recording_summary(recorder), err=True)
    if recorder is not None and recorder.failure is not None:
        raise ROSRuntimeError(str(recorder.failure))
    return result


@cli.command()
@click.argument("config_path", metavar="FILE", type=click.Path(path_type=Path))
@click.pass_context
def validate(ctx: click.Context, config_path: Path) -> None:
    """Check a deployment file: schema, plugins, robot, parameters, files. Connects, listens and moves nothing."""
    with exit_codes(bool(ctx.obj["debug"])):
        env = RobotEnvironment.from_yaml(config_path)
        check_deployment(env, base_dir=config_path.parent)
        click.echo(
            f"ok: {config_path} — robot {env.hal.robot_id} via {env.hal.adapter}, skill {env.vla.id}, "
            f"{len(env.sensors)} sensor(s), {env.rate_hz:g} Hz, safety {env.safety.client}"
        )


@cli.command()
@click.option("--output", "-o", type=click.Path(path_type=Path, dir_okay=False), default=None)
@click.option(
    "--kind",
    type=click.Choice(sorted(FILE_MODELS)),
    default="deployment",
    show_default=True,
    help="Which file: a deployment, a simulation scene or a benchmark suite.",
)
def schema(output: Path | None, kind: str) -> None:
    """Write the JSON Schema of a configuration file (stdout by default)."""
    text = schema_json(kind)
    if output is None:
        click.echo(text, nl=False)
    else:
        output.write_text(text, encoding="utf-8")
        click.echo(f"wrote {output}", err=True)


@cli.command()
@click.option("--robot", "robot_id", default="so101_follower", show_default=True, help="Robot manifest id.")
@click.option("--port", required=True, help="Serial device of the arm's servo bus, e.g. /dev/ttyACM0.")
@click.option(
    "--output",
    "-o",
    required=True,
    type=click.Path(path_type=Path, dir_okay=False),
    help="Calibration file to write (.json, or YAML for any other suffix).",
)
@click.option("--baudrate", type=click.IntRange(min=1), default=1_000_000, show_default=True)
@click.option("--record-s", type=Seconds(1.0), default=15.0, show_default=True, help="Seconds to record the ranges.")
@click.option("--invert", multiple=True, metavar="JOINT", help="A joint whose servo turns backwards (repeatable).")
@click.pass_context
def calibrate(
    ctx: click.Context,
    *,
    robot_id: str,
    port: str,
    output: Path,
    baudrate: int,
    record_s: float,
    invert: tuple[str, ...],
) -> None:
    """Record an SO-100/SO-101 arm's middle pose and joint ranges into a calibration file."""
    with exit_codes(bool(ctx.obj["debug"])):
        manifest = load_robot_manifest(robot_id)
        unknown = sorted(set(invert) - set(manifest.joint_names))
        if unknown:
            raise ROSConfigError(
                f"unknown joint(s) {unknown}; joints: {', '.join(manifest.joint_names)}", field="--invert"
            )
        from openral_hal.feetech.calibrate import calibrate as calibrate_arm  # noqa: PLC0415 - pyserial: the 'serial' extra

        calibrate_arm(
            manifest,
            port,
            output,
            baudrate=baudrate,
            record_s=record_s,
            directions=dict.fromkeys(invert, -1),
            prompt=lambda message: click.prompt(message, default="", show_default=False),
            say=click.echo,
        )


cli.add_command(dataset)
cli.add_command(record)
cli.add_command(replay)
cli.add_command(sim)
cli.add_command(benchmark)
cli.add_command(serve)


def main() -> None:
    """Console entry point."""
    cli(prog_name="openral")


__all__ = ["EXIT_CONFIG", "EXIT_OK", "cli", "main"]
