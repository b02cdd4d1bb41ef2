"""The ``openral`` command: YAML in, exit code out."""

from __future__ import annotations

import logging
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType

import click
import structlog

from openral_cli.errors import EXIT_CONFIG, EXIT_OK, EXIT_RUNTIME, EXIT_SIGINT, EXIT_SIGTERM, exit_codes
from openral_cli.report import format_run_result
from openral_cli.status import StatusLine
from openral_core import RobotEnvironment, ROSDeadlineMissed, RunResult
from openral_core.schema import robot_environment_schema_json
from openral_observability import semconv, tracer
from openral_runner.base import InferenceRunnerBase
from openral_runner.factory import build_runner

_STOP_EXIT_CODES = {"signal:SIGINT": EXIT_SIGINT, "signal:SIGTERM": EXIT_SIGTERM, "faults": EXIT_RUNTIME}


def _configure_logging(debug: bool) -> None:
    """Logs go to stderr so stdout carries only results (``--json``)."""
    structlog.configure(
        processors=[
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="%H:%M:%S"),
            structlog.dev.ConsoleRenderer(colors=sys.stderr.isatty()),
        ],
        wrapper_class=structlog.make_filtering_bound_logger(logging.DEBUG if debug else logging.INFO),
        logger_factory=structlog.PrintLoggerFactory(file=sys.stderr),
        cache_logger_on_first_use=True,
    )


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--debug", is_flag=True, help="Show tracebacks and debug logs.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """openral: run a robot skill at a steady rate, safely, with every tick traced."""
    ctx.obj = {"debug": debug}
    _configure_logging(debug)


@cli.command()
@click.option(
    "--config",
    "config_path",
    required=True,
    type=click.Path(path_type=Path, dir_okay=False),
    help="Deployment file (RobotEnvironment YAML).",
)
@click.option("--max-ticks", type=click.IntRange(min=0), default=None, help="Stop after this many ticks.")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), default=None, help="Stop after S seconds.")
@click.option("--json", "as_json", is_flag=True, help="Print the RunResult as JSON on stdout, nothing else.")
@click.pass_context
def deploy(ctx: click.Context, config_path: Path, max_ticks: int | None, duration: float | None, as_json: bool) -> None:
    """Run a deployment until --max-ticks, --duration, Ctrl-C or a safety stop."""
    debug = bool(ctx.obj["debug"])
    with (
        exit_codes(debug),
        tracer().start_as_current_span(semconv.SPAN_CLI_COMMAND, attributes={semconv.ATTR_CLI_COMMAND: "deploy"}),
    ):
        env = RobotEnvironment.from_yaml(config_path)
        result = _deploy(env, config_path.parent, max_ticks, duration, quiet=as_json)
        click.echo(result.model_dump_json(indent=2) if as_json else format_run_result(result))
        code = _STOP_EXIT_CODES.get(result.stop_reason, EXIT_OK)
        if result.stop_reason == "estop":
            code = EXIT_RUNTIME
    raise SystemExit(code)


def _deploy(
    env: RobotEnvironment, base_dir: Path, max_ticks: int | None, duration: float | None, *, quiet: bool
) -> RunResult:
    runner, skill = build_runner(env, base_dir=base_dir)
    skill.configure()
    try:
        skill.activate()
        runner.activate()
        try:
            with _stop_on_signals(runner), StatusLine(runner, sys.stderr):
                try:
                    return runner.run(max_ticks, duration_s=duration)
                except ROSDeadlineMissed as exc:
                    if exc.run_result is not None and not quiet:
                        click.echo(format_run_result(exc.run_result), err=True)
                    raise
        finally:
            runner.deactivate()
    finally:
        skill.shutdown()


@contextmanager
def _stop_on_signals(runner: InferenceRunnerBase) -> Iterator[None]:
    """SIGINT/SIGTERM finish the current tick and end the run; a second SIGINT aborts at once."""

    def handler(signum: int, _frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        runner.request_stop(f"signal:{name}")
        signal.signal(signum, signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


@cli.command()
@click.argument("config_path", metavar="FILE", type=click.Path(path_type=Path, dir_okay=False))
@click.pass_context
def validate(ctx: click.Context, config_path: Path) -> None:
    """Check a deployment file: schema, plugins, robot, skill parameters. Touches no hardware."""
    with exit_codes(bool(ctx.obj["debug"])):
        env = RobotEnvironment.from_yaml(config_path)
        _runner, skill = build_runner(env, base_dir=config_path.parent)
        skill.shutdown()
        click.echo(
            f"ok: {config_path} — robot {env.hal.robot_id} via {env.hal.adapter}, skill {env.vla.id}, "
            f"{len(env.sensors)} sensor(s), {env.rate_hz:g} Hz, safety {env.safety.client}"
        )


@cli.command()
@click.option("--output", "-o", type=click.Path(path_type=Path, dir_okay=False), default=None)
def schema(output: Path | None) -> None:
    """Write the JSON Schema of the deployment file (stdout by default)."""
    text = robot_environment_schema_json()
    if output is None:
        click.echo(text, nl=False)
    else:
        output.write_text(text, encoding="utf-8")
        click.echo(f"wrote {output}", err=True)


def main() -> None:
    """Console entry point."""
    cli(prog_name="openral")


__all__ = ["EXIT_CONFIG", "EXIT_OK", "cli", "main"]
