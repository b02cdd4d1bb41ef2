"""``--real-time`` (``sim run``, ``benchmark run``): rows paced by the wall clock, never paired with virtual rows."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from openral_cli.main import cli

ROOT = Path(__file__).resolve().parents[2]
MOCK_SCENE = ROOT / "scenes" / "sim" / "mock_reach.yaml"
FAST_MOCK = "{step_size: 0.5, tolerance: 0.3, control_hz: 50.0}"
"""The mock task at 50 Hz with big steps: an episode in real time takes a few slots of 20 ms."""


def _scene(tmp_path: Path) -> Path:
    scene = tmp_path / "reach.yaml"
    text = MOCK_SCENE.read_text(encoding="utf-8").replace("cameras:", f"env_kwargs: {FAST_MOCK}\ncameras:")
    scene.write_text(text, encoding="utf-8")
    return scene


def test_sim_run_in_real_time_reports_its_timing_and_how_it_kept_up(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    args = ["sim", "run", "--config", str(scene), "--skill", "mock_reach_expert", "--n-episodes", "3", "--no-cameras"]
    result = CliRunner().invoke(cli, [*args, "--real-time", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["timing"] == "measured"
    assert report["pc_success"] == 100.0
    live = report["real_time"]
    assert 0 < live["steps_per_s"] <= 60.0  # paced at 50 Hz, not free-running
    assert all(e["real_time"]["policy_ticks"] + e["real_time"]["held_slots"] == e["steps"] for e in report["episodes"])
    line = CliRunner().invoke(cli, [*args, "--real-time"]).stdout
    assert "real time:" in line
    assert "steps/s" in line
    virtual = json.loads(CliRunner().invoke(cli, [*args, "--json"]).stdout)
    assert virtual["timing"] == "virtual"
    assert "real_time" not in virtual


def test_benchmark_run_in_real_time_names_the_machine_and_refuses_to_pair_with_a_virtual_run(tmp_path: Path) -> None:
    suite = tmp_path / "suite.yaml"
    suite.write_text(
        f"name: reach\nruns:\n  - {{scene: {_scene(tmp_path)}, skill: mock_reach_expert, n_episodes: 3}}\n"
    )
    out = {mode: tmp_path / f"{mode}.json" for mode in ("measured", "virtual")}
    page = tmp_path / "measured.html"
    for mode, extra in (("measured", ["--real-time", "--html", str(page)]), ("virtual", [])):
        result = CliRunner().invoke(cli, ["benchmark", "run", "--config", str(suite), "--out", str(out[mode]), *extra])
        assert result.exit_code == 0, result.output
    measured = json.loads(out["measured"].read_text())
    (row,) = measured["results"]
    assert row["timing"] == "measured"
    assert row["real_time"]["steps_per_s"] > 0
    assert measured["provenance"]["real_time"]["rows"] == [row["label"]]
    assert "real_time" not in json.loads(out["virtual"].read_text())["provenance"]
    text = page.read_text(encoding="utf-8")
    assert '<section id="real-time">' in text
    refused = CliRunner().invoke(cli, ["benchmark", "compare", str(out["virtual"]), str(out["measured"])])
    assert refused.exit_code != 0
    assert "A's row ran with virtual latency and B's with measured" in refused.output


PICK_SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"
PICK_POLICY = ROOT / "models" / "so101_pick_mlp.onnx"


@pytest.mark.slow
def test_a_served_policy_in_real_time_is_paced_and_every_chunk_comes_from_the_server(tmp_path: Path) -> None:
    scene = tmp_path / "pick.yaml"
    scene.write_text(PICK_SCENE.read_text(encoding="utf-8").replace("max_steps: 100", "max_steps: 15"))
    suite = tmp_path / "suite.yaml"
    suite.write_text(
        f"name: pick\nruns:\n  - {{scene: {scene}, skill: onnx_policy, skill_params: {{model: {PICK_POLICY}}}, "
        "n_episodes: 2}\n"
    )
    out = tmp_path / "served.json"
    args = ["benchmark", "run", "--config", str(suite), "--workers", "2", "--serve", "--real-time", "--out", str(out)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    document = json.loads(out.read_text())
    (row,) = document["results"]
    assert row["timing"] == "measured"
    assert document["provenance"]["real_time"]["rows"] == [row["label"]]
    assert document["provenance"]["served"]["max_batch"] == 2
    assert row["served"]["served"] >= 2  # the first chunk of each episode, at least, came from the one server
    for episode in row["episodes"]:
        live = episode["real_time"]
        assert live["policy_ticks"] + live["held_slots"] == episode["steps"]
        assert live["wall_s"] >= episode["steps"] * 0.9 / episode["control_hz"]  # paced at the scene's rate
