"""``openral deploy --dataset-out`` cut into episodes, or kept as a ring whose highlights a key saves."""

from __future__ import annotations

import json
from pathlib import Path

from click.testing import CliRunner

from openral_cli.main import cli
from openral_dataset.check import check_dataset

DEPLOYMENT = (
    "name: modes\nrate_hz: 30\n"
    "hal: {robot_id: so101_follower, adapter: so10x_follower, params: {emulate: true}}\n"
    "vla: {id: hello}\n"
)


def _config(tmp_path: Path) -> Path:
    config = tmp_path / "deploy.yaml"
    config.write_text(DEPLOYMENT)
    return config


def _info(root: Path) -> dict[str, int]:
    info: dict[str, int] = json.loads((root / "meta" / "info.json").read_text())
    return info


def test_episode_every_s_commits_a_long_run_as_episodes_of_that_length(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    result = CliRunner().invoke(
        cli,
        ["deploy", "--config", str(_config(tmp_path)), "--dataset-out", str(out), "--vcodec", "h264",
         "--max-ticks", "40", "--episode-every-s", "0.5"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert check_dataset(out).problems == []
    info = _info(out)
    assert (info["total_episodes"], info["total_frames"]) == (3, 40)  # 15 + 15 + the 10 under way at the end


def test_the_highlight_key_saves_the_ring_as_one_episode_and_nothing_else_is_written(
    deploy_process, tmp_path: Path
) -> None:
    out = tmp_path / "ds"
    proc = deploy_process(
        ["deploy", "--config", str(_config(tmp_path)), "--dataset-out", str(out), "--vcodec", "h264",
         "--duration", "60", "--highlight-s", "1"],
        keys=True,
    )  # fmt: skip
    proc.wait_for("ticks ")  # the live status line: the run has ticked, the ring holds rows
    proc.press("s")
    proc.wait_for("highlight saved")
    proc.press("q")
    code, _ = proc.finish(timeout=60)
    assert code == 0, proc.stderr
    assert check_dataset(out).problems == []
    info = _info(out)
    assert info["total_episodes"] == 1
    assert 1 <= info["total_frames"] <= 30  # at most the ring's one second


def test_a_recording_mode_without_a_dataset_names_the_missing_option(tmp_path: Path) -> None:
    result = CliRunner().invoke(cli, ["deploy", "--config", str(_config(tmp_path)), "--highlight-s", "5"])
    assert result.exit_code == 2
    assert "--dataset-out" in result.output
