"""``openral benchmark compare``: two reports paired by scene and seed, refused where they cannot be."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from openral_cli.main import cli
from openral_core import ROSConfigError
from openral_sim.benchmark.compare import compare_reports, load_report, paired_steps

ROOT = Path(__file__).resolve().parents[3]
MOCK_SCENE = ROOT / "scenes" / "sim" / "mock_reach.yaml"


def report(skill: str, outcomes: list[tuple[bool, int | None]], **row: Any) -> dict[str, Any]:
    """A report of one completed row on scene ``pick`` whose episode k has seed k."""
    episodes = [
        {"episode_idx": k, "seed": k, "success": ok, "steps": 100, "steps_to_success": steps}
        for k, (ok, steps) in enumerate(outcomes)
    ]
    base = {"label": f"pick/{skill}", "scene": "pick", "env": "so101", "env_id": "pick", "skill": skill}
    base |= {"seeds": [0, len(episodes) - 1], "status": "completed", "episodes": episodes, **row}
    return {"suite": "s", "results": [base]}


def test_success_is_compared_on_the_same_seeds() -> None:
    a = report("a", [(True, 50)] * 6 + [(False, None)] * 14)
    b = report("b", [(True, 40)] * 6 + [(True, 60)] * 9 + [(False, None)] * 5)
    (row,) = compare_reports(a, b)["rows"]
    assert row["n_pairs"] == 20
    assert (row["pc_success_a"], row["pc_success_b"]) == (30.0, 75.0)
    assert row["difference_pp"] == pytest.approx(45.0)
    assert row["discordant"] == {"only_a": 0, "only_b": 9}
    assert row["mcnemar_p"] == pytest.approx(2 / 2**9)
    low, high = row["difference_pp_ci95"]
    assert 0 < low < 45 < high < 100
    steps = row["steps_to_success"]
    assert steps["n_both_succeeded"] == 6
    assert steps["mean_difference"] == -10.0
    assert steps["b_faster"] == 6
    assert steps["sign_test_p"] == pytest.approx(2 / 2**6)


def test_episodes_pair_by_seed_not_by_position() -> None:
    a = report("a", [(True, 10), (False, None)])
    b = report("b", [(True, 10), (False, None)])
    b["results"][0]["episodes"].reverse()
    (row,) = compare_reports(a, b)["rows"]
    assert row["discordant"] == {"only_a": 0, "only_b": 0}


def test_the_bootstrap_interval_is_seeded_and_brackets_the_mean() -> None:
    a = [30, 40, 50, 60, 70, None]
    b = [25, 41, 44, 58, 61, 80]
    first, second = paired_steps(a, b), paired_steps(a, b)
    assert first == second
    low, high = first["mean_difference_ci95"]
    assert first["mean_difference"] == pytest.approx(-4.2)
    assert low < -4.2 < high


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"env_id": "place"}, "env_id 'pick' and B's 'place'"),
        ({"seeds": [0, 99]}, "seeds"),
        ({"scene": "push"}, "scene 'pick' is in A's report and not in B's"),
        ({"timing": "measured"}, "A's row ran with virtual latency and B's with measured; .* depend on the machine"),
    ],
)
def test_rows_that_cannot_be_paired_are_refused_naming_the_difference(change: dict[str, Any], words: str) -> None:
    a = report("a", [(True, 5)] * 4)
    b = report("b", [(True, 5)] * 4, **change)
    with pytest.raises(ROSConfigError, match=words):
        compare_reports(a, b)


def test_a_row_that_does_not_name_its_timing_pairs_as_virtual() -> None:
    a = report("a", [(True, 5)] * 4)  # a report written before rows named their timing
    b = report("b", [(True, 5)] * 4, timing="virtual")
    (row,) = compare_reports(a, b)["rows"]
    assert row["n_pairs"] == 4
    with pytest.raises(ROSConfigError, match="A's row ran with measured latency and B's with virtual"):
        compare_reports(report("a", [(True, 5)] * 4, timing="measured"), b)


def test_episode_lengths_must_agree_where_both_reports_name_them() -> None:
    lerobot = {"max_steps": 280, "step_limit": "lerobot"}
    openpi = {"max_steps": 220, "step_limit": "openpi"}
    with pytest.raises(ROSConfigError, match="A's row has max_steps 280 and B's 220"):
        compare_reports(report("a", [(True, 5)] * 4, **lerobot), report("b", [(True, 5)] * 4, **openpi))
    # A report written before rows named their length still pairs with one that does.
    (row,) = compare_reports(report("a", [(True, 5)] * 4), report("b", [(True, 5)] * 4, **openpi))["rows"]
    assert row["n_pairs"] == 4


def test_seeds_in_one_report_only_are_refused() -> None:
    a = report("a", [(True, 5)] * 4)
    b = report("b", [(True, 5)] * 4)
    b["results"][0]["episodes"][-1]["seed"] = 40
    with pytest.raises(ROSConfigError, match=r"2 seed\(s\) ran in only one report \(first: 3\)"):
        compare_reports(a, b)


def test_a_seed_run_twice_in_a_row_is_refused() -> None:
    a = report("a", [(True, 5)] * 3)
    b = report("b", [(True, 5)] * 3)
    b["results"][0]["episodes"][2]["seed"] = 1
    a["results"][0]["episodes"][1]["seed"] = 2
    with pytest.raises(ROSConfigError, match="runs a seed more than once"):
        compare_reports(a, b)


@pytest.mark.parametrize(
    "row",
    [
        {"status": "completed", "scene": "x", "episodes": [{"success": True}]},  # an older report: no seeds
        {"status": "completed", "episodes": [{"seed": 0, "success": True}]},  # no scene
        {"status": "completed", "scene": "x", "episodes": [{"seed": 0, "success": True, "steps_to_success": "3"}]},
        {"status": "completed", "scene": "x", "episodes": "none"},
        {"status": "completed", "scene": "x", "episodes": [{"seed": 0, "success": True, "smoothness": 3}]},
        {"status": "completed", "scene": "x", "episodes": [{"seed": 0, "success": 1, "smoothness": {"jerk_rms": ""}}]},
    ],
)
def test_a_file_that_is_no_report_is_refused_in_one_line(tmp_path: Path, row: dict[str, Any]) -> None:
    path = tmp_path / "old.json"
    path.write_text(json.dumps({"results": [row]}))
    with pytest.raises(ROSConfigError, match=r"^A: .*not a benchmark report with per-episode seeds"):
        load_report(path, field="A")


def with_smoothness(document: dict[str, Any], jerks: list[float | None]) -> dict[str, Any]:
    """``document`` whose episode k recorded jerk ``jerks[k]`` and one reversal per second more than its seed."""
    for episode, jerk in zip(document["results"][0]["episodes"], jerks, strict=True):
        episode["smoothness"] = {"commands": 100, "jerk_rms": jerk, "reversals_per_s": episode["seed"] + 1.0}
    return document


def test_smoothness_is_paired_by_seed_with_a_bootstrap_interval_and_a_sign_test() -> None:
    outcomes: list[tuple[bool, int | None]] = [(True, 50)] * 8
    a = with_smoothness(report("a", outcomes), [10.0, 12.0, 9.0, 11.0, 10.0, 14.0, 8.0, None])
    b = with_smoothness(report("b", outcomes), [7.0, 9.0, 8.0, 8.0, 6.0, 10.0, 9.0, 5.0])
    b["results"][0]["episodes"].reverse()  # pairs by seed, not by position
    (row,) = compare_reports(a, b)["rows"]
    jerk = row["smoothness"]["jerk_rms"]
    assert jerk["n_pairs"] == 7  # seed 7 has no value in A
    assert jerk["mean_a"] == pytest.approx(74 / 7)
    assert jerk["mean_b"] == pytest.approx(57 / 7)
    assert jerk["mean_difference"] == pytest.approx(-17 / 7)
    low, high = jerk["mean_difference_ci95"]
    assert low < -17 / 7 < high < 0
    assert (jerk["b_lower"], jerk["b_higher"]) == (6, 1)
    assert jerk["sign_test_p"] == pytest.approx(2 * (1 + 7) / 2**7)
    reversals = row["smoothness"]["reversals_per_s"]
    assert reversals["mean_difference"] == 0.0
    assert reversals["sign_test_p"] == 1.0  # every pair tied: no evidence either way
    assert row["smoothness"]["ee_path_length_m"] is None  # neither recorded it


def test_a_report_without_smoothness_still_compares_and_says_it_is_unavailable(tmp_path: Path) -> None:
    outcomes: list[tuple[bool, int | None]] = [(True, 50), (False, None)]
    older, newer = report("a", outcomes), with_smoothness(report("b", outcomes), [1.0, 2.0])
    for a, b in ((older, newer), (newer, older)):
        (row,) = compare_reports(a, b)["rows"]
        assert row["smoothness"] is None
        assert row["discordant"] == {"only_a": 0, "only_b": 0}
    paths = [tmp_path / "old.json", tmp_path / "new.json"]
    for path, document in zip(paths, (older, newer), strict=True):
        path.write_text(json.dumps(document), encoding="utf-8")
    text = CliRunner().invoke(cli, ["benchmark", "compare", *map(str, paths), "--html", str(tmp_path / "ab.html")])
    assert text.exit_code == 0, text.output
    assert "smoothness B − A: unavailable" in text.output
    assert "unavailable (not recorded)" in (tmp_path / "ab.html").read_text(encoding="utf-8")


def test_compare_two_runs_of_a_suite_from_the_command_line(tmp_path: Path) -> None:
    out = {}
    for skill in ("zero", "mock_reach_expert"):
        suite = tmp_path / f"{skill}.yaml"
        suite.write_text(f"name: reach\nruns:\n  - {{scene: {MOCK_SCENE}, skill: {skill}, n_episodes: 8}}\n")
        out[skill] = tmp_path / f"{skill}.json"
        result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--out", str(out[skill])])
        assert result.exit_code == 0, result.output
    result = CliRunner().invoke(
        cli, ["benchmark", "compare", str(out["zero"]), str(out["mock_reach_expert"]), "--json"]
    )
    assert result.exit_code == 0, result.output
    (row,) = json.loads(result.output)["rows"]
    assert (row["pc_success_a"], row["pc_success_b"]) == (0.0, 100.0)
    assert row["mcnemar_p"] == pytest.approx(2 / 2**8)
    # Both runs recorded what they sent: jerk pairs every seed where both episodes sent four commands or more.
    steps = [[e["steps"] for e in json.loads(out[s].read_text())["results"][0]["episodes"]] for s in out]
    assert row["smoothness"]["jerk_rms"]["n_pairs"] == sum(min(x, y) >= 4 for x, y in zip(*steps, strict=True)) > 0
    assert row["smoothness"]["ee_path_length_m"] is None  # the mock env reports no end effector
    text = CliRunner().invoke(cli, ["benchmark", "compare", str(out["zero"]), str(out["mock_reach_expert"])])
    assert "mock_reach: 0.0 % → 100.0 %, +100.0 pp (95 % CI +54.1 to +100.0), McNemar p 0.0078" in text.output


def test_benchmark_run_with_a_baseline_compares_in_the_same_run(tmp_path: Path) -> None:
    suites = {}
    for skill in ("zero", "mock_reach_expert"):
        suites[skill] = tmp_path / f"{skill}.yaml"
        suites[skill].write_text(f"name: reach\nruns:\n  - {{scene: {MOCK_SCENE}, skill: {skill}, n_episodes: 6}}\n")
    baseline = tmp_path / "zero.json"
    first = CliRunner().invoke(
        cli, ["benchmark", "run", "--config", str(suites["zero"]), "--workers", "2", "--out", str(baseline)]
    )
    assert first.exit_code == 0, first.output
    page = tmp_path / "expert.html"
    expert = ["benchmark", "run", "--config", str(suites["mock_reach_expert"]), "--baseline", str(baseline)]
    result = CliRunner().invoke(cli, [*expert, "--json", "--html", str(page)])
    assert result.exit_code == 0, result.output
    document = json.loads(result.output)
    (row,) = document["comparison"]["rows"]
    assert (row["pc_success_a"], row["pc_success_b"], row["mcnemar_p"]) == (0.0, 100.0, pytest.approx(2 / 2**6))
    assert document["results"][0]["speedup"] is None  # a run of two workers is no speed reference
    # Every episode counts in time to success: the expert's half-way step exists, the zero policy's never does.
    solved = document["results"][0]["time_to_success"]
    assert solved["p50"] is not None
    assert solved["solved_by"][-1][1] == 1.0
    assert json.loads(baseline.read_text())["results"][0]["time_to_success"]["p50"] is None
    # The run's own page carries the comparison beside its results.
    text = page.read_text(encoding="utf-8")
    assert '<section id="comparison">' in text
    assert "+100.0 pp" in text


def test_the_html_page_shows_a_and_b_side_by_side_and_escapes_what_users_named(tmp_path: Path) -> None:
    a = report("a", [(True, 50)] * 6 + [(False, None)] * 14, scene="<b>pick</b>")
    b = report("b", [(True, 40)] * 6 + [(True, 60)] * 9 + [(False, None)] * 5, scene="<b>pick</b>")
    paths = [tmp_path / "a.json", tmp_path / "b.json"]
    for path, document in zip(paths, (a, b), strict=True):
        path.write_text(json.dumps(document), encoding="utf-8")
    page_path = tmp_path / "ab.html"
    result = CliRunner().invoke(cli, ["benchmark", "compare", *map(str, paths), "--html", str(page_path)])
    assert result.exit_code == 0, result.output
    page = page_path.read_text(encoding="utf-8")
    assert "&lt;b&gt;pick&lt;/b&gt;" in page
    assert "<b>pick" not in page
    for text in ("30.0 %", "75.0 %", "+45.0 pp", "0 / 9 / 20", "-10.0"):
        assert text in page, text
    assert "<script" not in page
    assert "http" not in page, "the page fetches nothing"


def test_a_report_that_is_missing_or_no_regular_file_is_refused_without_waiting(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match=r"^B: file not found"):
        load_report(tmp_path / "absent.json", field="B")
    pipe = tmp_path / "pipe.json"
    os.mkfifo(pipe)  # nobody writes to it: reading it as a file would wait for ever
    with pytest.raises(ROSConfigError, match=r"^B: .*FIFO"):
        load_report(pipe, field="B")
