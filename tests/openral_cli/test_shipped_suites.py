"""Every shipped benchmark suite is runnable as written: its scenes load, its skills and their parameters build."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from openral_cli.sim import _check_rows, _load_rows
from openral_core import BenchmarkSuite, ROSDependencyMissing
from openral_sim import build

SUITES = sorted((Path(__file__).resolve().parents[2] / "benchmarks" / "suites").glob("*.yaml"))


@pytest.mark.parametrize("suite_file", SUITES, ids=lambda p: p.stem)
def test_a_shipped_suite_resolves_every_row(suite_file: Path) -> None:
    suite = BenchmarkSuite.from_yaml(suite_file)
    try:
        rows = _load_rows(suite, suite_file, hashlib.sha256(), render_all=False)
        _check_rows(rows, build, on_ray=False)
    except ROSDependencyMissing as exc:
        pytest.skip(str(exc))
    assert len(rows) == len(suite.runs)
    assert all(run.min_success is None or run.skill not in ("random", "zero") for run, _ in rows)
