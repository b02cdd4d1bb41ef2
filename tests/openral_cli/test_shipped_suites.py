"""Every shipped benchmark suite is runnable as written: its scenes load, its skills and their parameters build."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from openral_core import BenchmarkSuite, ROSDependencyMissing
from openral_sim.benchmark.rows import check_rows, load_rows

SUITES = sorted((Path(__file__).resolve().parents[2] / "benchmarks" / "suites").glob("*.yaml"))
SLOW_SUITES = {"libero_pro"}
"""Suites whose every environment takes long to build (20 LIBERO tasks): checked in the slow tail; their scenes are
checked one by one in the fast suite (tests/openral_sim/test_libero_pro.py)."""


@pytest.mark.parametrize(
    "suite_file",
    [pytest.param(path, marks=pytest.mark.slow) if path.stem in SLOW_SUITES else path for path in SUITES],
    ids=lambda p: p.stem,
)
def test_a_shipped_suite_resolves_every_row(suite_file: Path) -> None:
    suite = BenchmarkSuite.from_yaml(suite_file)
    try:
        rows = load_rows(suite, suite_file, hashlib.sha256(), render_all=False)
        check_rows(rows, on_ray=False)
    except ROSDependencyMissing as exc:
        pytest.skip(str(exc))
    assert len(rows) == len(suite.runs)
    assert all(run.min_success is None or run.skill not in ("random", "zero") for run, _ in rows)
