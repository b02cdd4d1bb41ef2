"""``openral sim run`` and ``openral benchmark run``: evaluation in simulation with numbers you can trust.

Both drive ``SimRunner`` (one env step per tick, the same skills, safety and observers as on a
robot). Results carry LeRobot's aggregate names (``pc_success``, ``avg_sum_reward``,
``avg_max_reward``) and the success rate's Wilson 95 % interval. With ``--json`` stdout carries
one JSON document and nothing else: anything a simulator prints goes to stderr.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click

from openral_cli.command_lifecycle import command_span
from openral_cli.console import CONSOLE_OPTION, ConsoleAddress, attach_console, with_console
from openral_cli.errors import EXIT_OK, EXIT_RUNTIME, exit_codes
from openral_cli.options import json_object
from openral_cli.recording import (
    FOXGLOVE_OPTION,
    MCAP_OPTION,
    VCODEC_OPTION,
    dataset_entry,
    print_foxglove,
    recorder_of,
    recording_summary,
    with_observers,
    with_viewers,
)
from openral_cli.signals import StopSignals
from openral_core import BenchmarkSuite, ROSRuntimeError, SimEnvironment


@contextlib.contextmanager
def _stdout_to_stderr(active: bool) -> Iterator[None]:
    """While active, file descriptor 1 is stderr: simulators and Ray cannot spoil a JSON stdout."""
    if not active:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


REAL_TIME_OPTION = click.option(
    "--real-time",
    is_flag=True,
    help="Pace the simulation by the wall clock while the policy infers on its worker (virtual_latency: "
    "measured): a slow policy loses steps as on a robot, and outcomes depend on this machine.",
)


@click.group()
def sim() -> None:
    """Evaluate skills in simulation."""


@sim.command("run")
@click.option("--config", "config_path", required=True, type=click.Path(path_type=Path), help="Scene file.")
@click.option("--skill", "skill_id", required=True, help="Skill id (openral.skills), e.g. so101_pick_expert.")
@click.option("--skill-params", default=None, help="The skill's parameters as a JSON object.")
@click.option("--n-episodes", type=click.IntRange(min=1), default=None, help="Overrides the scene's episode count.")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Seed of episode 0 (episode i: seed + i).")
@click.option(
    "--set",
    "assignments",
    multiple=True,
    metavar="KEY=VALUE",
    help="Override a scene field, validated as the file's own (repeatable; value in YAML): "
    "--set virtual_latency.ticks=2 --set executor.indexing=stale_start.",
)
@click.option(
    "--save-video",
    type=click.Path(path_type=Path, file_okay=False),
    default=None,
    help="Write MP4s of the first episodes (the scene's first camera) here.",
)
@click.option("--videos", type=click.IntRange(min=1), default=3, show_default=True, help="Episodes filmed.")
@click.option("--dataset-out", type=click.Path(path_type=Path, file_okay=False), default=None)
@click.option("--resume", is_flag=True, help="Add the episodes to the dataset already in --dataset-out.")
@click.option(
    "--no-cameras", is_flag=True, help="Render none of the scene's cameras (state-only skills: tens of ms a step less)."
)
@REAL_TIME_OPTION
@VCODEC_OPTION
@CONSOLE_OPTION
@FOXGLOVE_OPTION
@MCAP_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print one JSON document on stdout, nothing else.")
@click.option("--otlp-endpoint", default=None, help="Export telemetry to this OTLP endpoint.")
@click.pass_context
def sim_run(
    ctx: click.Context,
    *,
    config_path: Path,
    skill_id: str,
    skill_params: str | None,
    n_episodes: int | None,
    seed: int | None,
    assignments: tuple[str, ...],
    save_video: Path | None,
    videos: int,
    dataset_out: Path | None,
    resume: bool,
    no_cameras: bool,
    real_time: bool,
    vcodec: str,
    console: ConsoleAddress | None,
    foxglove_port: int | None,
    rosbag: Path | None,
    as_json: bool,
    otlp_endpoint: str | None,
) -> None:
    """Run a skill on a scene's episodes and report success with its 95 % interval.

    ``--dataset-out``, ``--save-video``, ``--mcap``, ``--foxglove`` and ``--console`` add the observer
    entries they stand for to the scene's own ``observers:``, as they do on ``deploy``.
    """
    from openral_sim import build, evaluation  # noqa: PLC0415 - for the simulation commands only
    from openral_sim.benchmark.rows import with_overrides  # noqa: PLC0415

    code = EXIT_OK
    with StopSignals() as signals, exit_codes(bool(ctx.obj["debug"])):
        scene = with_overrides(SimEnvironment.from_yaml(config_path, overrides=assignments), n_episodes, seed)
        if no_cameras:
            scene = scene.model_copy(update={"cameras": []})
        if real_time:
            scene = scene.model_copy(update={"virtual_latency": "measured"})
        params = json_object(skill_params, "--skill-params")
        if dataset_out is not None:  # first, as on deploy: it hears each tick before the viewers
            scene = with_observers(scene, dataset_entry(dataset_out, resume=resume, vcodec=vcodec), first=True)
        if save_video is not None:
            scene = with_observers(
                scene, evaluation.episode_video_entry(save_video, episodes=videos, prefix=scene.name)
            )
        scene = with_viewers(scene, rosbag=rosbag, foxglove_port=foxglove_port, config_path=config_path)
        scene = with_console(scene, console)
        watched: list[Any] = []

        def on_runner(runner: Any) -> None:
            watched.extend(runner.observers)
            _stop_on(runner, signals, recording=dataset_out is not None)
            if foxglove_port is not None:
                print_foxglove(runner.observers)  # on stderr: a --json stdout stays one document

        with (
            _stdout_to_stderr(as_json),
            command_span(
                "sim run", config_path, otlp_endpoint=otlp_endpoint, otlp_protocol=None, trace_sample_ratio=None
            ),
        ):
            batch = build.run_episodes(scene, skill_id, params, on_runner=on_runner)
        recorders = [recorder_of(watched)] if dataset_out is not None and watched else []
        failed = next((r.failure for r in recorders if r.failure is not None), None)
        if failed is not None:  # the episodes after the write failure were not recorded: no result to report
            for recorder in recorders:
                click.echo(recording_summary(recorder), err=True)
            raise ROSRuntimeError(str(failed))
        report = {
            "scene": scene.name,
            "skill": skill_id,
            "skill_params": params,
            "seed": scene.seed,
            "timing": scene.timing,
            **evaluation.summarize(batch.episodes, batch),
            "episodes": [e.model_dump(mode="json") for e in batch.episodes],
        }
        if save_video is not None:
            report["videos"] = [str(p) for p in _videos_written(watched)]
        if as_json:
            click.echo(json.dumps(report, indent=2))
        else:
            click.echo(_summary_line(report))
            for recorder in recorders:
                click.echo(recording_summary(recorder), err=True)
        if signals.received is not None:
            code = signals.exit_code or EXIT_RUNTIME
    raise SystemExit(code)


def _stop_on(runner: Any, signals: StopSignals, *, recording: bool) -> None:
    """Stop signals, a recorder that can no longer write and the console's stop button all end the run."""
    signals.on_stop(runner.request_stop)
    if recording:
        recorder_of(runner.observers).on_failure = runner.request_stop
    attach_console(runner, stop=runner.request_stop)  # no-op without --console


def _videos_written(observers: list[Any]) -> list[Path]:
    """The files the ``--save-video`` writer wrote."""
    from openral_sim.video import EpisodeVideoWriter  # noqa: PLC0415 (PyAV: the 'dataset' extra)

    return next((o.written for o in observers if isinstance(o, EpisodeVideoWriter)), [])


def _summary_line(report: dict[str, Any]) -> str:
    from openral_sim.evaluation import real_time_note  # noqa: PLC0415

    low, high = report["pc_success_ci95"]
    return (
        f"{report['scene']} / {report['skill']}: {report['pc_success']:.1f} % success "
        f"({report['n_success']}/{report['n_episodes']}, 95 % CI {low:.1f}–{high:.1f} %), "
        f"avg sum reward {report['avg_sum_reward']:.3f}, avg max reward {report['avg_max_reward']:.3f}"
        f"{real_time_note(report)}"
    )


@click.group()
def benchmark() -> None:
    """Run benchmark suites: several scenes × skills, with confidence intervals and provenance."""


@benchmark.command("run")
@click.option("--config", "config_path", required=True, type=click.Path(path_type=Path), help="Suite file.")
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Processes here (at most the largest row's episodes and the CPUs this process may use).",
)
@click.option("--ray", "ray_address", default=None, help="Run on Ray: 'auto', 'local' or a cluster address.")
@click.option(
    "--threads-per-worker",
    type=click.IntRange(min=0, max=1024),
    default=None,
    help="Threads each numeric library (BLAS, OpenMP, PyTorch, ONNX Runtime) may use in each worker process "
    "[default: 1 with several workers or Ray; --workers 1 runs here, unlimited]. A count with --workers 1 runs the "
    "episodes in one worker process; 0: no limit. A skill parameter that names a count wins.",
)
@click.option(
    "--min-success",
    type=click.FloatRange(0, 100),
    default=None,
    help="Exit 1 when any row's pc_success (percent) is below this.",
)
@click.option("--out", type=click.Path(path_type=Path, dir_okay=False), default=None, help="Write the JSON here.")
@click.option(
    "--html",
    "html_path",
    type=click.Path(path_type=Path),
    default=None,
    help="Also write the report as one self-contained HTML page with plots (needs the 'report' extra).",
)
@click.option(
    "--videos",
    "video_dir",
    type=click.Path(path_type=Path, file_okay=False),
    default=None,
    help="Film the first episodes of each row (the suite's 'videos' count) into this folder.",
)
@click.option(
    "--baseline",
    "baseline_path",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="An earlier run's JSON (--out): compared with this run on the same seeds when their rows pair; "
    "a --workers 1 run of this suite on this machine also gives rows their speedup and efficiency.",
)
@click.option(
    "--serve",
    is_flag=True,
    help="Load each row's policy once in a policy server; the workers ask it as remote_policy clients.",
)
@click.option(
    "--serve-max-batch",
    type=click.IntRange(1, 1024),
    default=None,
    help="--serve: requests one inference takes (default: one per worker).",
)
@click.option(
    "--serve-gpus",
    type=click.FloatRange(min=0),
    default=0.0,
    show_default=True,
    help="--serve with --ray: GPUs for the server's Ray actor.",
)
@REAL_TIME_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print the JSON document on stdout, nothing else.")
@click.pass_context
def benchmark_run(
    ctx: click.Context,
    *,
    config_path: Path,
    workers: int,
    ray_address: str | None,
    threads_per_worker: int | None,
    min_success: float | None,
    out: Path | None,
    html_path: Path | None,
    video_dir: Path | None,
    baseline_path: Path | None,
    serve: bool,
    serve_max_batch: int | None,
    serve_gpus: float,
    real_time: bool,
    as_json: bool,
) -> None:
    """Evaluate every row of a suite; report success with 95 % intervals, latency percentiles and provenance.

    Every row's scene and skill are built once before the first episode, so a typo in the last row
    fails at once. A row that fails while running ends the suite: the rows finished by then and the
    failed row (marked, with its error) are still written, then the command exits non-zero.

    With --serve each row's policy is served once (a Ray actor with --ray) and the episodes run as
    its remote_policy clients; with the scene's virtual_latency the outcomes are the local run's.

    With --real-time every row runs paced by the wall clock (virtual_latency: measured); the
    provenance names the rows whose outcomes depend on this machine.
    """
    started = time.perf_counter()
    # The simulation stack loads for the simulation commands only.
    from openral_sim import report_files  # noqa: PLC0415
    from openral_sim.benchmark.baseline import (  # noqa: PLC0415
        check_baseline,
        compare_with,
        load_baseline,
        threads_note,
    )
    from openral_sim.benchmark.compare import comparison_lines  # noqa: PLC0415
    from openral_sim.benchmark.provenance import provenance  # noqa: PLC0415
    from openral_sim.benchmark.report import markdown_table, suite_document, table_line  # noqa: PLC0415
    from openral_sim.benchmark.rows import in_real_time, load_rows  # noqa: PLC0415
    from openral_sim.benchmark.suite_run import ServeOptions, run_suite, worker_processes  # noqa: PLC0415
    from openral_sim.evaluation import Evaluator  # noqa: PLC0415
    from openral_sim.worker_environment import thread_report  # noqa: PLC0415

    code = EXIT_OK
    with exit_codes(bool(ctx.obj["debug"])):
        # Paths the reports cannot be written to, and a missing matplotlib, fail now, not after the run.
        if out is not None:
            report_files.check_output_file(out, option="--out", example_name="report.json")
        if html_path is not None:
            from openral_sim import html_report  # noqa: PLC0415 - matplotlib: the 'report' extra

            html_report.check_writable(html_path)
        suite = BenchmarkSuite.from_yaml(config_path)
        baseline = load_baseline(baseline_path) if baseline_path is not None else None
        hasher = hashlib.sha256(config_path.read_bytes())
        rows = load_rows(suite, config_path, hasher, render_all=video_dir is not None)
        if real_time:
            rows = in_real_time(rows)
        compare = baseline is not None and check_baseline(baseline, rows)
        processes = workers
        if ray_address is None:
            processes, note = worker_processes(workers, rows)
            if note is not None:
                click.echo(note, err=True)
        serving = ServeOptions(max_batch=serve_max_batch, gpus=serve_gpus) if serve else None
        evaluator = Evaluator(workers=processes, ray_address=ray_address, threads_per_worker=threads_per_worker)
        if baseline is not None and baseline.one_process:
            note = threads_note(baseline, evaluator.threads)
            if note is not None:
                click.echo(note, err=True)
        with _stdout_to_stderr(as_json), evaluator:
            outcome = run_suite(
                rows,
                evaluator,
                started=started,
                baseline=baseline.rows if baseline is not None and baseline.one_process else None,
                serve=serving,
                video_dir=video_dir,
                videos=suite.videos,
                min_success=min_success,
                on_row=None if as_json else lambda row: click.echo(table_line(row), err=True),
            )
            worker_threads = None if outcome.error is not None else evaluator.in_worker(thread_report)
        document = suite_document(
            suite.name,
            outcome,
            wall_s=time.perf_counter() - started,
            provenance=provenance(
                hasher.hexdigest(),
                processes,
                ray_address,
                requested=workers,
                served=None if serving is None else serving.described(evaluator.processes),
                baseline=baseline_path,
                measured_rows=[row.label for row in rows if row.scene.timing != "virtual"],
                threads_per_worker=evaluator.threads,
                worker_threads=worker_threads,
            ),
        )
        if compare and baseline is not None and outcome.error is None:
            document["comparison"] = compare_with(baseline, document)
        text = json.dumps(document, indent=2)
        if out is not None:
            report_files.write_whole(out, text + "\n", what="the JSON report")
        if html_path is not None:
            html_report.write(document, html_path)
        if as_json:
            click.echo(text)
        else:
            click.echo(markdown_table(outcome.results, evaluator.processes))
            for line in comparison_lines(document["comparison"]) if "comparison" in document else []:
                click.echo(line)
        if outcome.error is not None:
            raise outcome.error
        if outcome.below_min_success:
            click.echo("below --min-success: " + "; ".join(outcome.below_min_success), err=True)
            code = EXIT_RUNTIME
    raise SystemExit(code)


@benchmark.command("compare")
@click.argument("report_a", type=click.Path(path_type=Path, dir_okay=False))
@click.argument("report_b", type=click.Path(path_type=Path, dir_okay=False))
@click.option("--out", type=click.Path(path_type=Path, dir_okay=False), default=None, help="Write the JSON here.")
@click.option(
    "--html",
    "html_path",
    type=click.Path(path_type=Path, dir_okay=False),
    default=None,
    help="Also write A and B side by side as one self-contained HTML page.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the comparison as JSON on stdout, nothing else.")
@click.pass_context
def benchmark_compare(
    ctx: click.Context, *, report_a: Path, report_b: Path, out: Path | None, html_path: Path | None, as_json: bool
) -> None:
    """Compare two reports (--out of benchmark run) of the same suite, scene by scene on the same seeds.

    Success of B − A with Newcombe's paired 95 % interval and the exact McNemar test on the
    discordant seeds; steps to success on the seeds both solved (paired bootstrap interval, sign
    test). Rows that cannot be paired (a scene or seed in one report only, another environment)
    are refused, naming what differs.
    """
    from openral_sim import html_comparison, report_files  # noqa: PLC0415
    from openral_sim.benchmark.compare import compare_reports, comparison_lines, load_report  # noqa: PLC0415

    with exit_codes(bool(ctx.obj["debug"])):
        if out is not None:
            report_files.check_output_file(out, option="--out", example_name="comparison.json")
        if html_path is not None:
            report_files.check_output_file(html_path, option="--html", example_name="comparison.html")
        comparison = compare_reports(load_report(report_a, field="A"), load_report(report_b, field="B"))
        text = json.dumps(comparison, indent=2)
        if out is not None:
            report_files.write_whole(out, text + "\n", what="the JSON comparison")
        if html_path is not None:
            html_comparison.write(comparison, html_path)
        if as_json:
            click.echo(text)
        else:
            for line in comparison_lines(comparison):
                click.echo(line)


__all__ = ["benchmark", "sim"]
