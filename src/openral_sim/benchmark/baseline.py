"""The reference run of ``benchmark run --baseline``: for speed-ups, and for a paired comparison.

A baseline is an earlier ``--out`` report. When it is a one-process run (``--workers 1``, no Ray)
of the same rows, each row gets its speed-up and per-worker efficiency against it. When its rows
pair with this run's (one row per scene on each side, the same environment and seeds), the
report also compares this run (B) with it (A) on the same seeds
(:mod:`openral_sim.benchmark.compare`). A report that serves neither use is refused before any
episode runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from openral_core import ROSConfigError
from openral_sim.benchmark.compare import PAIRED_FIELDS, compare_reports, load_report, timing_problem
from openral_sim.benchmark.rows import SuiteRow

BASELINE_OPTION = "--baseline"


@dataclass(frozen=True)
class Baseline:
    """An earlier run's report, and whether it is a one-process run (a speed reference)."""

    document: dict[str, Any]
    one_process: bool

    @property
    def rows(self) -> list[dict[str, Any]]:
        """The report's rows (``results``)."""
        return list(self.document["results"])


def load_baseline(path: Path) -> Baseline:
    """An earlier ``benchmark run --out`` report, checked whole now: nothing in it can fail after the run.

    Raises:
        ROSConfigError: Not such a report (unreadable, not JSON, no results, per-episode seeds or provenance).
    """
    document = load_report(path, field=BASELINE_OPTION)
    try:
        provenance = document["provenance"]
        one_process = provenance["workers"] == 1 and provenance["ray"] is None
    except (KeyError, TypeError) as exc:
        raise ROSConfigError(f"{path} is not a benchmark report: no provenance ({exc})", field=BASELINE_OPTION) from exc
    return Baseline(document, bool(one_process))


def threads_note(baseline: Baseline, threads: int | None) -> str | None:
    """The line that says a one-process baseline ran with another thread limit than this run, else ``None``.

    Its speed-ups still hold as measured, but they then measure the thread limit as well as the
    workers. A report that does not record the limit ran one process unlimited, as one process did then.
    """
    before = baseline.document["provenance"].get("threads_per_worker")
    if before == threads:
        return None
    return (
        f"{BASELINE_OPTION}: its run allowed {_threads(before)} per library, this one {_threads(threads)}: "
        "speed-ups and efficiency measure both the workers and that difference"
    )


def _threads(threads: int | None) -> str:
    return "unlimited threads" if threads is None else f"{threads} thread(s)"


def references(baseline: Sequence[dict[str, Any]], rows: Sequence[SuiteRow]) -> dict[str, float]:
    """Each row's episodes per second in the baseline, by label: same label, same episodes (seeds).

    Raises:
        ROSConfigError: A row the baseline did not complete with the same seeds.
    """
    completed = {row.get("label"): row for row in baseline if row.get("status") == "completed"}
    found = {}
    for row in rows:
        reference = completed.get(row.label)
        if reference is None or reference.get("seeds") != row.seeds or not reference.get("episodes_per_s"):
            raise ROSConfigError(
                f"no completed row {row.label!r} with seeds {row.seeds} and episodes_per_s in the baseline",
                field=BASELINE_OPTION,
                hint="run the same suite with --workers 1 --out FILE first",
            )
        found[row.label] = float(reference["episodes_per_s"])
    return found


def pairing_problem(baseline: Baseline, rows: Sequence[SuiteRow]) -> str | None:
    """Why this run cannot be compared with the baseline on the same seeds, or ``None`` when it can."""
    scenes = [row.scene.name for row in rows]
    repeated = sorted({scene for scene in scenes if scenes.count(scene) > 1})
    if repeated:
        return f"this suite runs scene {repeated[0]!r} in more than one row"
    completed: dict[str, list[dict[str, Any]]] = {}
    for reference in baseline.rows:
        if reference.get("status") == "completed":
            completed.setdefault(str(reference.get("scene")), []).append(reference)
    for row in rows:
        found = completed.get(row.scene.name, [])
        if len(found) != 1:
            return f"the baseline has {len(found)} completed rows of scene {row.scene.name!r}, not one"
        head = row.head()
        mismatch = timing_problem(found[0], head, ("the baseline", "this run"))
        if mismatch is not None:
            return f"scene {row.scene.name!r}: {mismatch}"
        for key in (*PAIRED_FIELDS, "seeds"):
            if found[0].get(key) != head[key]:
                return f"scene {row.scene.name!r} has {key} {found[0].get(key)!r} in the baseline, {head[key]!r} here"
    return None


def check_baseline(baseline: Baseline, rows: Sequence[SuiteRow]) -> bool:
    """Whether this run will be compared with the baseline; refuses a baseline of no use.

    Raises:
        ROSConfigError: Neither a one-process run (for speed-ups) nor pairable with this run.
    """
    problem = pairing_problem(baseline, rows)
    if problem is not None and not baseline.one_process:
        raise ROSConfigError(
            f"the baseline is neither a --workers 1 run (for speed-ups) nor a run this one pairs with: {problem}",
            field=BASELINE_OPTION,
            hint="run the same suite (scenes and seeds) with another policy, or with --workers 1, and --out FILE",
        )
    return problem is None


def compare_with(baseline: Baseline, document: dict[str, Any]) -> dict[str, Any]:
    """This run's report (B) compared with the baseline's rows of the same scenes (A)."""
    scenes = {row.get("scene") for row in document["results"] if row.get("status") == "completed"}
    reference = {**baseline.document, "results": [row for row in baseline.rows if row.get("scene") in scenes]}
    return compare_reports(reference, document)
