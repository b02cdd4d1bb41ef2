"""Every row of a suite through one evaluator: checked first, then run in order until one fails.

A row that fails while running ends the suite: the rows finished by then and the failed row
(marked, with its error) are kept, and the rows after it are named as not run.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from openral_sim import evaluation
from openral_sim.benchmark.baseline import references
from openral_sim.benchmark.policy_host import RowPolicyServer, serve_row
from openral_sim.benchmark.rows import SuiteRow, check_rows, completed_row, failed_row
from openral_sim.build import SkillFailed


@dataclass(frozen=True)
class ServeOptions:
    """Each row's policy served once, its episodes run as the server's clients.

    Attributes:
        max_batch: Requests one inference takes (``None``: one per process that asks).
        gpus: GPUs for the server's Ray actor (on Ray only).
    """

    max_batch: int | None = None
    gpus: float = 0.0

    def described(self, processes: int | None) -> dict[str, Any]:
        """How the rows were served, for the provenance: ``max_batch`` is ``None`` on Ray (one per cluster process)."""
        return {"max_batch": self.max_batch or processes, "gpus": self.gpus}


@dataclass
class SuiteOutcome:
    """What a suite's run gives back: its report rows, and the error that ended it early if one did.

    Attributes:
        results: The report's rows in suite order, the failed one last.
        startup_s: From the command's start until the first row could run.
        below_min_success: ``label: pc % < threshold %`` for each completed row below its threshold.
        error: What failed a row; the rows after it did not run.
        not_run: The labels of the rows after the failed one.
    """

    results: list[dict[str, Any]]
    startup_s: float
    below_min_success: list[str] = field(default_factory=list)
    error: BaseException | None = None
    not_run: list[str] = field(default_factory=list)


def worker_processes(requested: int, rows: Sequence[SuiteRow]) -> tuple[int, str | None]:
    """The worker processes to start: no more than the largest row has episodes, nor the CPUs here run at once.

    An episode is the smallest unit a process takes, so more processes than that would idle; more
    than the CPUs would only share them. Returns the count and, when it is fewer than asked for,
    the line that says so.
    """
    most = max(row.scene.n_episodes for row in rows)
    processes = evaluation.worker_processes(requested, most)
    if processes >= requested:
        return processes, None
    note = (
        f"--workers {requested}: starting {processes} worker processes "
        f"({evaluation.usable_cpus()} CPUs usable here, at most {most} episodes in a row)"
    )
    return processes, note


def run_suite(
    rows: Sequence[SuiteRow],
    evaluator: evaluation.Evaluator,
    *,
    started: float,
    baseline: Sequence[dict[str, Any]] | None = None,
    serve: ServeOptions | None = None,
    video_dir: Path | None = None,
    videos: int = 0,
    min_success: float | None = None,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> SuiteOutcome:
    """Check every row, then run them in order; a row that fails ends the suite (see the module's docstring).

    Args:
        rows: The suite's rows (:func:`~openral_sim.benchmark.rows.load_rows`).
        evaluator: Where the episodes run (its workers start building the first row's scene at once).
        started: ``time.perf_counter()`` when the command started, for ``startup_s``.
        baseline: A one-process report's rows: completed rows get speed-up and efficiency.
        serve: Serve each row's policy once instead of building it in every worker.
        video_dir: Film each row's first ``videos`` episodes into this folder.
        min_success: The lowest acceptable ``pc_success`` of a row that sets none itself.
        on_row: Called with each completed row as it finishes (progress).

    Raises:
        ROSConfigError: A row cannot be built, or the baseline lacks one; before any episode runs.
    """
    if serve is None:  # served, a worker's skill is a client of a server that is not up yet
        # The workers start (and build the first row's scene) while this process checks the rows.
        first = rows[0]
        evaluator.warm_up(evaluation.EpisodeUnit(first.scene, first.run.skill, dict(first.run.skill_params)))
    check_rows(rows, on_ray=evaluator.ray_address is not None)
    speeds = references(baseline, rows) if baseline is not None else {}
    evaluator.wait_warm()
    outcome = SuiteOutcome(results=[], startup_s=time.perf_counter() - started)
    for index, row in enumerate(rows):
        row_started = time.perf_counter()
        server: RowPolicyServer | None = None
        served: dict[str, int] | None = None
        try:
            skill_id, params = row.run.skill, dict(row.run.skill_params)
            if serve is not None:
                server = serve_row(row.scene, row.run, evaluator=evaluator, max_batch=serve.max_batch, gpus=serve.gpus)
                skill_id, params = server.skill_id, server.params
            units = evaluator.schedule(row.scene, skill_id, params, row.scene.n_episodes)
            if video_dir is not None and row.scene.cameras and videos:
                entry = evaluation.episode_video_entry(
                    video_dir, episodes=videos, prefix=f"{row.scene.name}_{skill_id}", option="--videos"
                )
                units = evaluation.with_observers(units, entry)
            batch = evaluator.run(units)
        except SkillFailed as exc:
            outcome.error = exc
            outcome.results.append(failed_row(row, exc, exc.batch.episodes))
        except (Exception, KeyboardInterrupt) as exc:
            outcome.error = exc
            outcome.results.append(failed_row(row, exc, []))
        finally:
            served = server.close() if server is not None else None
        if outcome.error is not None:
            outcome.not_run = [later.label for later in rows[index + 1 :]]
            break
        result = completed_row(
            row,
            batch,
            wall_s=time.perf_counter() - row_started,
            processes=evaluator.processes,
            one_process_per_s=speeds.get(row.label),
            served=served,
        )
        threshold = row.run.min_success if row.run.min_success is not None else min_success
        result["min_success"] = threshold
        if threshold is not None and result["pc_success"] < threshold:
            outcome.below_min_success.append(f"{row.label}: {result['pc_success']:.1f} % < {threshold:g} %")
        outcome.results.append(result)
        if on_row is not None:
            on_row(result)
    return outcome
