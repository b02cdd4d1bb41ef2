"""A command's life up to its exit code: telemetry set up and flushed, one root span, the deployment run."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import click
from opentelemetry.trace import Span

from openral_cli.errors import EXIT_OK, EXIT_RUNTIME, EXIT_SIGINT, EXIT_SIGTERM
from openral_cli.report import format_run_result
from openral_cli.signals import StopSignals
from openral_core import RobotEnvironment, ROSStopRequested, RunResult, StopReason
from openral_observability import semconv, tracer
from openral_observability.propagation import context_from_env
from openral_observability.setup import setup
from openral_runner.factory import build_runner
from openral_runner.hardware import HardwareRunner

STOP_EXIT_CODES = {
    StopReason.SIGINT: EXIT_SIGINT,
    StopReason.SIGTERM: EXIT_SIGTERM,
    StopReason.FAULTS: EXIT_RUNTIME,
    StopReason.ESTOP: EXIT_RUNTIME,
}


@contextmanager
def command_span(
    command: str,
    config_path: Path,
    *,
    otlp_endpoint: str | None,
    otlp_protocol: str | None,
    trace_sample_ratio: float | None,
) -> Iterator[Span]:
    """Set telemetry up, run the body under one ``cli.command`` span, and flush telemetry on every exit.

    The span continues the trace named by a ``TRACEPARENT`` environment variable when there is one.
    """
    telemetry = setup(endpoint=otlp_endpoint, protocol=otlp_protocol, sample_ratio=trace_sample_ratio)
    try:
        with tracer().start_as_current_span(
            semconv.SPAN_CLI_COMMAND,
            context=context_from_env(),
            attributes={semconv.ATTR_CLI_COMMAND: command, semconv.ATTR_CLI_CONFIG: str(config_path)},
        ) as span:
            yield span
    finally:
        telemetry.shutdown()


def print_result(result: RunResult, *, as_json: bool, err: bool = False) -> None:
    click.echo(result.model_dump_json(indent=2) if as_json else format_run_result(result), err=err)


def exit_code(stop_reason: StopReason) -> int:
    """The process exit code of a run that stopped for ``stop_reason``."""
    return STOP_EXIT_CODES.get(stop_reason, EXIT_OK)


@contextmanager
def running(
    env: RobotEnvironment,
    base_dir: Path,
    *,
    signals: StopSignals,
) -> Iterator[HardwareRunner]:
    """Build the deployment, start it, and yield the active runner; close everything on the way out.

    Stop signals reach the runner from here on, and a stop during start-up unwinds what was
    started (``ROSStopRequested``). The observers are closed even when the runner never activated.
    """
    with ExitStack() as stack:
        runner, skill = build_runner(env, base_dir=base_dir)
        for observer in runner.observers:
            stack.callback(observer.close)  # idempotent; for runs that never reached activate()
        signals.on_stop(runner.request_stop)
        # The escape: the robot's torque off even if the main thread is stuck (bounded by StopSignals).
        signals.on_force(runner.hal.disconnect)
        stack.callback(skill.shutdown)
        signals.check()
        skill.configure()
        signals.check()
        skill.activate()
        runner.activate()  # checks for a stop between its own steps and rolls back
        stack.callback(runner.deactivate)
        yield runner


def stopped_before_start(env: RobotEnvironment, exc: ROSStopRequested) -> RunResult:
    """The result of a run stopped before its first tick (everything started was closed)."""
    return RunResult(
        runner_name="hardware_runner",
        skill_id=env.vla.id,
        rate_hz=env.rate_hz,
        n_ticks=0,
        stop_reason=StopReason(exc.reason),
    )
