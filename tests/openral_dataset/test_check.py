"""``openral dataset check``: damaged metadata is a ``problem:`` line (never a traceback); a staging area a note."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from openral_cli.main import cli
from openral_dataset import layout, schema
from openral_dataset.check import check_dataset
from openral_dataset.writer import LeRobotDatasetSink


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    root = tmp_path / "ds"
    sink = LeRobotDatasetSink(root, fps=30, robot_type="test_arm", joint_names=["a", "b"], vcodec="h264")
    for task in ("pick", "place"):
        sink.begin_episode(task)
        for k in range(3):
            sink.add_row({schema.STATE: [0.1 * k, 0.0], schema.ACTION: [0.1 * k, 0.5]}, {})
        sink.end_episode(success=True)
    sink.close()
    return root


def _check(root: Path) -> tuple[int, str]:
    result = CliRunner().invoke(cli, ["dataset", "check", str(root)])
    return result.exit_code, result.output


@pytest.mark.parametrize(
    ("path", "content", "expected"),
    [
        (layout.INFO_PATH, b"42", "problem: meta/info.json: holds a JSON number, not an object"),
        (layout.TASKS_PATH, None, "problem: meta/tasks.parquet: unreadable"),
        (layout.STATS_PATH, b'{"observation.state": {"mean": [1, 2', "problem: meta/stats.json: not valid JSON"),
        (layout.STATS_PATH, b'{"observation.state": [1, 2]}', "problem: meta/stats.json: must map each feature"),
    ],
)
def test_damaged_metadata_is_a_problem_line_and_exit_1(
    dataset: Path, path: str, content: bytes | None, expected: str
) -> None:
    target = dataset / path
    target.write_bytes(target.read_bytes()[:40] if content is None else content)  # None: truncated
    code, output = _check(dataset)
    assert code == 1, output
    assert expected in output
    assert "Traceback" not in output


def test_a_staging_area_left_by_a_killed_recording_is_a_note_not_a_problem(dataset: Path) -> None:
    staged = dataset / layout.STAGING_DIR / "episode-000002"
    staged.mkdir(parents=True)
    (staged / "front.mp4").write_bytes(b"half an episode")

    report = check_dataset(dataset)
    assert report.problems == []
    assert [n for n in report.notes if n.startswith(f"{layout.STAGING_DIR}/")]
    code, output = _check(dataset)
    assert code == 0, output
    assert f"note: {layout.STAGING_DIR}/" in output
    assert "problem" not in output
