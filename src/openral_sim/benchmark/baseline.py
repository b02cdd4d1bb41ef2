"""A one-process run's report as the reference that rows' speed-up and efficiency are measured against."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from openral_core import ROSConfigError
from openral_sim.benchmark.rows import SuiteRow

BASELINE_OPTION = "--baseline"


def load_baseline(path: Path) -> list[dict[str, Any]]:
    """The rows of a one-process run's report, to measure speed-ups against.

    Raises:
        ROSConfigError: Not such a report (unreadable, not JSON, or not run with ``--workers 1`` here).
    """
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
        provenance = document["provenance"]
        one_process = provenance["workers"] == 1 and provenance["ray"] is None
        rows = document["results"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ROSConfigError(f"not a benchmark report: {exc}", field=BASELINE_OPTION) from exc
    if not one_process:
        raise ROSConfigError(
            "the baseline must be a --workers 1 run without --ray (the one-process reference)", field=BASELINE_OPTION
        )
    return list(rows)


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
