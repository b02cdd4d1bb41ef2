"""Provenance: the packages, machine and processes, and the serving and baseline only when the run had them."""

from __future__ import annotations

from importlib import metadata
from pathlib import Path

from openral_sim.benchmark.provenance import PROVENANCE_PACKAGES, git_revision, package_versions, provenance


def test_provenance_names_the_processes_started_and_asked_for_and_nothing_the_run_did_not_have() -> None:
    described = provenance("ab" * 32, 2, None, requested=8)
    assert (described["config_sha256"], described["workers"], described["workers_requested"]) == ("ab" * 32, 2, 8)
    assert described["ray"] is None
    assert set(described["packages"]) == set(PROVENANCE_PACKAGES)
    assert described["packages"]["numpy"] == metadata.version("numpy")
    assert "served" not in described
    assert "baseline" not in described
    assert "real_time" not in described
    assert described["machine"]["cpu_model"]


def test_provenance_names_the_rows_whose_outcomes_depend_on_the_machine() -> None:
    described = provenance("ab" * 32, 2, None, requested=2, measured_rows=["pick/act"])
    live = described["real_time"]
    assert live["rows"] == ["pick/act"]
    assert live["workers"] == 2
    assert live["cpus"] == described["machine"]["cpus"]
    assert live["cpu_model"] == described["machine"]["cpu_model"]
    assert "machine-dependent" in live["outcomes"]


def test_provenance_names_the_serving_and_the_baseline_last_when_given() -> None:
    described = provenance(
        "0" * 64, 1, "auto", requested=1, served={"max_batch": None, "gpus": 1.0}, baseline=Path("one.json")
    )
    assert list(described)[-2:] == ["served", "baseline"]
    assert described["served"] == {"max_batch": None, "gpus": 1.0}
    assert described["baseline"] == "one.json"
    assert described["ray"] == "auto"


def test_a_package_that_is_not_installed_has_no_version() -> None:
    assert package_versions(("numpy", "no-such-distribution-here")) == {
        "numpy": metadata.version("numpy"),
        "no-such-distribution-here": None,
    }


def test_outside_a_git_checkout_there_is_no_revision(tmp_path: Path) -> None:
    assert git_revision(tmp_path) is None


def test_in_a_git_checkout_the_revision_is_its_commit() -> None:
    revision = git_revision(Path(__file__).resolve().parent)
    assert revision is not None
    assert len(revision) == 40
    assert int(revision, 16) >= 0
