"""A suite's rows: scenes read with the row's overrides, cameras only where asked, and each row's report head."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import pytest

from openral_core import BenchmarkRun, BenchmarkSuite, ROSConfigError, SimEnvironment
from openral_sim.benchmark.rows import SuiteRow, failed_row, load_rows, with_overrides

ROOT = Path(__file__).resolve().parents[3]
MOCK_SCENE = ROOT / "scenes" / "sim" / "mock_reach.yaml"


def _suite(tmp_path: Path, *rows: str) -> Path:
    path = tmp_path / "suite.yaml"
    path.write_text("name: tiny\nruns:\n" + "".join(f"  - {row}\n" for row in rows), encoding="utf-8")
    return path


def test_rows_take_the_runs_overrides_and_render_cameras_only_where_asked(tmp_path: Path) -> None:
    suite_file = _suite(
        tmp_path,
        f"{{scene: {MOCK_SCENE}, skill: zero, n_episodes: 3, seed: 7}}",
        f"{{scene: {MOCK_SCENE}, skill: random, render_cameras: true, label: seen}}",
    )
    hasher = hashlib.sha256(b"suite")
    rows = load_rows(BenchmarkSuite.from_yaml(suite_file), suite_file, hasher, render_all=False)
    first, second = rows
    assert (first.scene.n_episodes, first.scene.seed, first.scene.cameras) == (3, 7, [])
    assert (second.scene.n_episodes, second.scene.seed) == (20, 0)  # the scene's own
    assert [camera.name for camera in second.scene.cameras] == ["top"]
    expected = hashlib.sha256(b"suite" + MOCK_SCENE.read_bytes() + MOCK_SCENE.read_bytes())
    assert hasher.hexdigest() == expected.hexdigest()  # every scene file is part of the suite's hash


def test_rendering_all_keeps_every_rows_cameras(tmp_path: Path) -> None:
    suite_file = _suite(tmp_path, f"{{scene: {MOCK_SCENE}, skill: zero}}")
    (row,) = load_rows(BenchmarkSuite.from_yaml(suite_file), suite_file, hashlib.sha256(), render_all=True)
    assert [camera.name for camera in row.scene.cameras] == ["top"]


def test_a_missing_scene_file_names_the_rows_field(tmp_path: Path) -> None:
    suite_file = _suite(tmp_path, f"{{scene: {MOCK_SCENE}, skill: zero}}", "{scene: nowhere.yaml, skill: zero}")
    with pytest.raises(ROSConfigError) as caught:
        load_rows(BenchmarkSuite.from_yaml(suite_file), suite_file, hashlib.sha256(), render_all=False)
    assert caught.value.field == "runs[1].scene"


def _row(**run: Any) -> SuiteRow:
    scene = SimEnvironment.from_yaml(MOCK_SCENE).model_copy(update={"n_episodes": 4, "seed": 10})
    return SuiteRow(BenchmarkRun(scene=str(MOCK_SCENE), skill="zero", **run), scene)


def test_a_row_is_labelled_scene_and_skill_unless_it_names_itself() -> None:
    assert _row().label == "mock_reach/zero"
    assert _row(label="mine").label == "mine"


def test_a_rows_head_names_its_first_and_last_seed() -> None:
    head = _row(skill_params={"a": 1}).head()
    assert head == {
        "label": "mock_reach/zero",
        "scene": "mock_reach",
        "env": "mock",
        "env_id": "reach",
        "skill": "zero",
        "skill_params": {"a": 1},
        "seeds": [10, 13],
        "timing": "virtual",
        "max_steps": 60,
    }


def test_a_rows_head_names_the_step_limit_convention_its_scene_names() -> None:
    row = _row()
    scene = row.scene.model_copy(update={"env_kwargs": {**row.scene.env_kwargs, "step_limit": "openpi"}})
    head = SuiteRow(row.run, scene).head()
    assert (head["step_limit"], head["max_steps"]) == ("openpi", 60)


def test_overrides_that_are_not_given_keep_the_scenes_values() -> None:
    scene = _row().scene
    assert with_overrides(scene, None, None) is scene
    assert (with_overrides(scene, None, 3).n_episodes, with_overrides(scene, None, 3).seed) == (4, 3)
    assert (with_overrides(scene, 9, None).n_episodes, with_overrides(scene, 9, None).seed) == (9, 10)


def test_a_failed_row_carries_its_error_and_episodes_and_no_success_rate() -> None:
    row = failed_row(_row(), KeyboardInterrupt(), [])
    assert row["status"] == "failed"
    assert row["error"] == "KeyboardInterrupt: interrupted"  # an exception without a message still says what
    assert row["episodes"] == []
    assert "pc_success" not in row
    assert failed_row(_row(), ValueError("bad"), [])["error"] == "ValueError: bad"
