"""Every shipped benchmark suite is runnable as written: its scenes load, its skills and their parameters build."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from openral_core import BenchmarkSuite, ROSDependencyMissing
from openral_sim.benchmark.rows import check_rows, load_rows

SUITES = sorted((Path(__file__).resolve().parents[2] / "benchmarks" / "suites").glob("*.yaml"))


@pytest.mark.parametrize("suite_file", SUITES, ids=lambda p: p.stem)
def test_a_shipped_suite_resolves_every_row(suite_file: Path) -> None:
    suite = BenchmarkSuite.from_yaml(suite_file)
    try:
        rows = load_rows(suite, suite_file, hashlib.sha256(), render_all=False)
        check_rows(rows, on_ray=False)
    except ROSDependencyMissing as exc:
        pytest.skip(str(exc))
    assert len(rows) == len(suite.runs)
    assert all(run.min_success is None or run.skill not in ("random", "zero") for run, _ in rows)
