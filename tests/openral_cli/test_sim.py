"""``openral sim run`` and ``openral benchmark run`` as a user runs them."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from openral_cli.main import cli
from openral_dataset.check import check_dataset
from openral_sim import evaluation

ROOT = Path(__file__).resolve().parents[2]
MOCK_SCENE = ROOT / "scenes" / "sim" / "mock_reach.yaml"


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def test_sim_run_json_puts_one_document_on_stdout_and_nothing_else() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "openral_cli", "sim", "run", "--config", str(MOCK_SCENE), "--skill", "random",
         "--n-episodes", "4", "--seed", "5", "--json"],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)  # the whole of stdout is one JSON document
    assert report["n_episodes"] == 4
    assert report["seed"] == 5
    assert [e["seed"] for e in report["episodes"]] == [5, 6, 7, 8]
    low, high = report["pc_success_ci95"]
    assert 0.0 <= low <= report["pc_success"] <= high <= 100.0
    assert {"avg_sum_reward", "avg_max_reward", "tick_ms", "inference_ms"} <= set(report)


def test_sim_run_records_a_dataset_the_checker_accepts(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    result = CliRunner().invoke(
        cli,
        ["sim", "run", "--config", str(MOCK_SCENE), "--skill", "mock_reach_expert", "--n-episodes", "3",
         "--dataset-out", str(out), "--vcodec", "h264", "--save-video", str(tmp_path / "videos"), "--videos", "2"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = check_dataset(out)
    assert report.problems == []
    assert report.episodes == 3
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["features"]["action"]["names"] == ["dx", "dy"]
    assert info["features"]["observation.environment_state"]["names"] == ["target_x", "target_y"]
    assert info["fps"] == 10
    assert sorted(p.name for p in (tmp_path / "videos").iterdir()) == [
        "mock_reach_episode0.mp4",
        "mock_reach_episode1.mp4",
    ]


def test_sim_run_mcap_and_foxglove_produce_what_deploys_do(tmp_path: Path, check_bag, check_foxglove_served) -> None:
    recording = tmp_path / "run.mcap"
    args = ["sim", "run", "--config", str(MOCK_SCENE), "--skill", "mock_reach_expert", "--n-episodes", "2",
            "--foxglove", "0", "--mcap", str(recording), "--json"]  # fmt: skip
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)  # the address goes to stderr: stdout stays one document
    check_foxglove_served(result.stderr)
    # One tick resets each episode (it has no world state yet), then one tick per step.
    steps = sum(e["steps"] for e in report["episodes"])
    check_bag(recording, ticks=steps + len(report["episodes"]), worlds=steps, attached=[MOCK_SCENE.name])


def test_sim_run_refuses_a_taken_dataset_folder_naming_the_flag_and_leaves_it_as_it_was(tmp_path: Path) -> None:
    taken = tmp_path / "taken"
    (taken / "meta").mkdir(parents=True)
    (taken / "meta" / "notes.txt").write_text("mine")
    args = ["sim", "run", "--config", str(MOCK_SCENE), "--skill", "zero", "--n-episodes", "1",
            "--dataset-out", str(taken)]  # fmt: skip
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 2, result.output
    assert "--dataset-out" in result.output
    assert (taken / "meta" / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in taken.iterdir()) == ["meta"]


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("max_step: 10", "max_step"),
        ("max_steps: 0", "max_steps"),
        ("success_key: done", "success_key"),
    ],
)
def test_a_wrong_scene_file_exits_2_with_one_line_naming_the_field(tmp_path: Path, text: str, field: str) -> None:
    base = MOCK_SCENE.read_text().replace("max_steps: 60\n", "")
    scene = _write(tmp_path / "scene.yaml", base + text + "\n")
    result = CliRunner().invoke(cli, ["sim", "run", "--config", str(scene), "--skill", "zero"])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output
    assert field in lines[0]


def test_set_overrides_a_scene_field_and_a_wrong_one_is_named_like_the_files_own() -> None:
    result = CliRunner().invoke(
        cli,
        ["sim", "run", "--config", str(MOCK_SCENE), "--skill", "zero", "--n-episodes", "2", "--json",
         "--set", "max_steps=3", "--set", "end_on_success=false"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert [e["steps"] for e in report["episodes"]] == [3, 3]  # the scene says 60
    wrong = CliRunner().invoke(
        cli, ["sim", "run", "--config", str(MOCK_SCENE), "--skill", "zero", "--set", "virtual_latency.tick=2"]
    )
    assert wrong.exit_code == 2
    assert "virtual_latency.tick: unknown key 'tick'; allowed keys: jitter_ticks, ticks" in wrong.output
    assert "did you mean 'ticks'?" in wrong.output


def test_bad_skill_params_exit_2_naming_the_option() -> None:
    result = CliRunner().invoke(
        cli, ["sim", "run", "--config", str(MOCK_SCENE), "--skill", "zero", "--skill-params", "{nope"]
    )
    assert result.exit_code == 2
    assert "--skill-params" in result.output


@pytest.mark.slow
def test_benchmark_run_reports_every_row_with_provenance_and_fails_below_min_success(tmp_path: Path) -> None:
    suite = _write(
        tmp_path / "suite.yaml",
        f"name: tiny\n"
        f"runs:\n"
        f"  - {{scene: {MOCK_SCENE}, skill: mock_reach_expert, n_episodes: 4}}\n"
        f"  - {{scene: {MOCK_SCENE}, skill: zero, n_episodes: 4, label: baseline}}\n",
    )
    out = tmp_path / "bench.json"
    result = CliRunner().invoke(
        cli, ["benchmark", "run", "--config", str(suite), "--workers", "2", "--min-success", "50", "--out", str(out)]
    )
    assert result.exit_code == 1  # the zero baseline is below 50 %
    assert "baseline" in result.output
    document = json.loads(out.read_text())
    rows = {row["label"]: row for row in document["results"]}
    assert rows["mock_reach/mock_reach_expert"]["pc_success"] == 100.0
    assert rows["baseline"]["pc_success"] == 0.0
    assert [e["episode_idx"] for e in rows["baseline"]["episodes"]] == [0, 1, 2, 3]
    provenance = document["provenance"]
    assert provenance["packages"]["mujoco"] is not None
    assert len(provenance["config_sha256"]) == 64
    assert provenance["workers"] == 2
    passing = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--min-success", "0"])
    assert passing.exit_code == 0, passing.output


def test_sim_run_with_a_skill_failing_every_step_exits_1_with_its_error_not_a_0_percent_result() -> None:
    # The SO-101 expert needs privileged values the mock scene does not expose: every step fails.
    proc = subprocess.run(
        [sys.executable, "-m", "openral_cli", "sim", "run", "--config", str(MOCK_SCENE), "--skill",
         "so101_pick_expert", "--n-episodes", "4", "--no-cameras", "--json"],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout == ""  # no success rate is reported for a skill that cannot run
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, proc.stderr
    assert "so101_pick_expert" in errors[0]
    assert "no privileged value 'grasp_pos'" in errors[0]


def _suite(tmp_path: Path, *rows: str) -> Path:
    return _write(tmp_path / "suite.yaml", "name: tiny\nruns:\n" + "".join(f"  - {row}\n" for row in rows))


def test_benchmark_refuses_a_typo_in_a_later_row_before_any_episode_runs(tmp_path: Path) -> None:
    suite = _suite(
        tmp_path,
        f"{{scene: {MOCK_SCENE}, skill: mock_reach_expert, n_episodes: 2}}",
        f"{{scene: {MOCK_SCENE}, skill: randm, n_episodes: 2}}",
    )
    out = tmp_path / "bench.json"
    result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--out", str(out)])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output  # no row ran: no progress line before the error
    assert lines[0].startswith("error: runs[1].skill: unknown skill 'randm'")
    assert "did you mean 'random'" in lines[0]
    assert not out.exists()


def test_benchmark_names_a_rows_bad_skill_parameter(tmp_path: Path) -> None:
    suite = _suite(
        tmp_path,
        f"{{scene: {MOCK_SCENE}, skill: zero, n_episodes: 1}}",
        f"{{scene: {MOCK_SCENE}, skill: random, n_episodes: 1, skill_params: {{sede: 1}}}}",
    )
    result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite)])
    assert result.exit_code == 2
    assert "error: runs[1].skill_params.sede: unknown key 'sede'" in result.output


def test_benchmark_writes_the_finished_rows_and_the_failed_one_when_a_row_fails_while_running(tmp_path: Path) -> None:
    suite = _suite(
        tmp_path,
        f"{{scene: {MOCK_SCENE}, skill: mock_reach_expert, n_episodes: 2}}",
        f"{{scene: {MOCK_SCENE}, skill: so101_pick_expert, n_episodes: 3, label: broken}}",
        f"{{scene: {MOCK_SCENE}, skill: zero, n_episodes: 2, label: after}}",
    )
    out = tmp_path / "bench.json"
    result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--out", str(out)])
    assert result.exit_code == 1, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, result.output
    assert "grasp_pos" in errors[0]
    document = json.loads(out.read_text())
    finished, failed = document["results"]
    assert finished["status"] == "completed"
    assert finished["pc_success"] == 100.0
    assert failed["label"] == "broken"
    assert failed["status"] == "failed"
    assert "grasp_pos" in failed["error"]
    assert "pc_success" not in failed  # a broken skill has no success rate, not 0 %
    assert [e["ended_by"] for e in failed["episodes"]] == ["faults"]
    assert document["not_run"] == ["after"]


@pytest.mark.slow
def test_benchmark_run_reports_episodes_per_second_and_efficiency_against_a_one_worker_baseline(
    tmp_path: Path,
) -> None:
    suite = _suite(tmp_path, f"{{scene: {MOCK_SCENE}, skill: mock_reach_expert, n_episodes: 6}}")
    one, two = tmp_path / "one.json", tmp_path / "two.json"
    alone = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--out", str(one)])
    assert alone.exit_code == 0, alone.output
    (reference,) = json.loads(one.read_text())["results"]
    assert reference["episodes_per_s"] == pytest.approx(6 / reference["wall_s"])
    assert reference["episodes_per_s_per_worker"] == reference["episodes_per_s"]
    assert reference["speedup"] is None  # nothing measured to compare with
    assert reference["efficiency"] is None
    assert reference["env_builds"] == 1

    result = CliRunner().invoke(
        cli,
        ["benchmark", "run", "--config", str(suite), "--workers", "2", "--baseline", str(one), "--out", str(two)],
    )
    assert result.exit_code == 0, result.output
    document = json.loads(two.read_text())
    (row,) = document["results"]
    untimed = [{k: v for k, v in e.items() if k != "timing"} for e in row["episodes"]]
    assert untimed == [{k: v for k, v in e.items() if k != "timing"} for e in reference["episodes"]]
    assert row["episodes_per_s_per_worker"] == pytest.approx(row["episodes_per_s"] / 2)
    assert row["speedup"] == pytest.approx(row["episodes_per_s"] / reference["episodes_per_s"])
    assert row["efficiency"] == pytest.approx(row["speedup"] / 2)
    assert 1 <= row["env_builds"] <= 2  # at most once per worker
    assert document["startup_s"] + row["wall_s"] <= document["wall_s"]
    efficiency = f"{row['efficiency']:.2f} ({row['speedup']:.2f}× on 2 workers)"
    assert f"{row['episodes_per_s']:.2f} | {efficiency} |" in result.output
    # The baseline ran here, unlimited; the workers ran with one thread per library, and the report says both.
    assert json.loads(one.read_text())["provenance"]["threads_per_worker"] is None
    assert document["provenance"]["threads_per_worker"] == 1
    assert document["provenance"]["worker_threads"]["variables"]["OMP_NUM_THREADS"] == "1"
    assert "--baseline: its run allowed unlimited threads per library, this one 1 thread(s)" in result.output

    # A report of several workers is no speed reference; the same suite on the same seeds pairs with it.
    compared = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--baseline", str(two), "--json"])
    assert compared.exit_code == 0, compared.output
    again = json.loads(compared.output)
    assert again["results"][0]["speedup"] is None
    (pair,) = again["comparison"]["rows"]
    assert (pair["difference_pp"], pair["mcnemar_p"]) == (0.0, 1.0)
    other = _suite(tmp_path, f"{{scene: {MOCK_SCENE}, skill: mock_reach_expert, n_episodes: 3}}")
    refused = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(other), "--baseline", str(two)])
    assert refused.exit_code == 2
    assert "error: --baseline: the baseline is neither a --workers 1 run" in refused.output
    assert "seeds [0, 5] in the baseline, [0, 2] here" in refused.output


def test_benchmark_refuses_a_baseline_without_the_suites_rows(tmp_path: Path) -> None:
    baseline = tmp_path / "base.json"
    baseline.write_text(json.dumps({"results": [], "provenance": {"workers": 1, "ray": None}}))
    suite = _suite(tmp_path, f"{{scene: {MOCK_SCENE}, skill: zero, n_episodes: 2}}")
    result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--baseline", str(baseline)])
    assert result.exit_code == 2
    assert "error: --baseline: no completed row 'mock_reach/zero' with seeds [0, 1]" in result.output


PICK_SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"
PICK_POLICY = ROOT / "models" / "so101_pick_mlp.onnx"


@pytest.mark.slow
def test_benchmark_run_served_loads_the_policy_once_and_gives_the_local_outcomes(tmp_path: Path) -> None:
    suite = _suite(
        tmp_path,
        f"{{scene: {PICK_SCENE}, skill: onnx_policy, skill_params: {{model: {PICK_POLICY}}}, n_episodes: 4}}",
    )
    local_out, served_out = tmp_path / "local.json", tmp_path / "served.json"
    local = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--out", str(local_out)])
    assert local.exit_code == 0, local.output
    served = CliRunner().invoke(
        cli, ["benchmark", "run", "--config", str(suite), "--workers", "2", "--serve", "--out", str(served_out)]
    )
    assert served.exit_code == 0, served.output
    (reference,) = json.loads(local_out.read_text())["results"]
    document = json.loads(served_out.read_text())
    (row,) = document["results"]
    untimed = [{k: v for k, v in e.items() if k != "timing"} for e in row["episodes"]]
    assert untimed == [{k: v for k, v in e.items() if k != "timing"} for e in reference["episodes"]]
    assert row["served"]["served"] > 4  # every chunk came from the one server
    assert row["served"]["largest_batch"] >= 1
    assert document["provenance"]["served"] == {"max_batch": 2, "gpus": 0.0}


def test_benchmark_refuses_to_serve_a_policy_of_one_row_per_request(tmp_path: Path) -> None:
    suite = _suite(tmp_path, f"{{scene: {PICK_SCENE}, skill: so101_pick_expert, n_episodes: 2}}")
    result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--serve"])
    assert result.exit_code != 0
    assert "cannot be served" in result.output


def _special_file(path: Path, kind: str) -> str:
    """Make ``path`` a FIFO, a null device node of its own or a link to a regular file; what the error calls it."""
    if kind == "fifo":
        os.mkfifo(path)
        return "a FIFO (named pipe)"
    if kind == "device":
        try:
            os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))  # a /dev/null of this test's own
        except PermissionError:
            pytest.skip("making a device node needs root")
        return "a character device"
    target = path.with_name("target.txt")
    target.write_text("kept", encoding="utf-8")
    path.symlink_to(target)
    return "a symbolic link"


@pytest.mark.parametrize(
    ("option", "kind"),
    [("--html", "fifo"), ("--html", "device"), ("--html", "link"), ("--out", "device"), ("--out", "link")],
)
def test_benchmark_refuses_a_report_path_that_is_not_a_regular_file_before_the_run(
    tmp_path: Path, option: str, kind: str
) -> None:
    target = tmp_path / "report"
    called = _special_file(target, kind)
    before = os.lstat(target)
    suite = _suite(tmp_path, f"{{scene: {MOCK_SCENE}, skill: zero, n_episodes: 1}}")
    result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), option, str(target)])
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1, result.output  # refused before any row ran
    assert lines[0].startswith(f"error: {option}: {target} is {called}, not a regular file")
    after = os.lstat(target)  # the same node, not a report renamed over it
    assert (after.st_mode, after.st_ino, after.st_rdev) == (before.st_mode, before.st_ino, before.st_rdev)
    if kind == "link":
        assert (tmp_path / "target.txt").read_text(encoding="utf-8") == "kept"


@pytest.mark.slow
def test_benchmark_starts_no_more_workers_than_units_and_cpus_and_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    started: list[int] = []

    class CountedPool(evaluation.ProcessPoolExecutor):
        def __init__(self, max_workers: int, **kwargs: Any) -> None:
            started.append(max_workers)
            if max_workers > 8:  # uncapped: fail here instead of starting them all
                raise AssertionError(f"a pool of {max_workers} processes")
            super().__init__(max_workers, **kwargs)

    monkeypatch.setattr(evaluation, "ProcessPoolExecutor", CountedPool)
    monkeypatch.setattr(evaluation, "usable_cpus", lambda: 2)  # whatever this machine has
    suite = _suite(
        tmp_path,
        f"{{scene: {MOCK_SCENE}, skill: zero, n_episodes: 3}}",
        f"{{scene: {MOCK_SCENE}, skill: zero, n_episodes: 1, label: one}}",
    )
    out = tmp_path / "bench.json"
    args = ["benchmark", "run", "--config", str(suite), "--workers", "1000", "--out", str(out)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert started == [2]  # one pool for the whole suite, of min(units, CPUs) processes
    notes = [line for line in result.output.splitlines() if line.startswith("--workers")]
    assert notes == ["--workers 1000: starting 2 worker processes (2 CPUs usable here, at most 3 episodes in a row)"]
    document = json.loads(out.read_text())
    assert (document["provenance"]["workers"], document["provenance"]["workers_requested"]) == (2, 1000)
    assert [row["n_episodes"] for row in document["results"]] == [3, 1]

    # Fewer units than CPUs: as many processes as the largest row has episodes.
    monkeypatch.setattr(evaluation, "usable_cpus", lambda: 64)
    one_row = _suite(tmp_path, f"{{scene: {MOCK_SCENE}, skill: zero, n_episodes: 2}}")
    result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(one_row), "--workers", "1000"])
    assert result.exit_code == 0, result.output
    assert started == [2, 2]
    assert "starting 2 worker processes (64 CPUs usable here, at most 2 episodes in a row)" in result.output
