"""The scene file model: where its relative paths point."""

from __future__ import annotations

from pathlib import Path

from openral_core import SimEnvironment
from openral_core.config import load_model_yaml

SCENE = "name: s\nenv: mock\ntask: reach\nmax_steps: 5\nenv_kwargs: {bddl: problems/pick.bddl}\n"


def test_a_scene_read_from_a_file_resolves_relative_paths_against_its_folder(tmp_path: Path) -> None:
    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "s.yaml").write_text(SCENE)
    scene = load_model_yaml(SimEnvironment, folder / "s.yaml")
    assert scene.base_dir == str(folder.resolve())
    assert scene.resolve_path(scene.env_kwargs["bddl"]) == folder.resolve() / "problems" / "pick.bddl"
    assert scene.resolve_path(str(tmp_path / "abs.bddl")) == tmp_path / "abs.bddl"
    # The folder travels with the scene (to worker processes and Ray tasks as JSON).
    assert SimEnvironment.model_validate_json(scene.model_dump_json()).base_dir == scene.base_dir


def test_a_base_dir_written_in_the_file_wins_and_a_scene_built_in_code_uses_the_working_directory(
    tmp_path: Path,
) -> None:
    (tmp_path / "s.yaml").write_text(SCENE + "base_dir: /data/problems\n")
    assert load_model_yaml(SimEnvironment, tmp_path / "s.yaml").base_dir == "/data/problems"
    in_code = SimEnvironment(name="s", env="mock", task="reach", max_steps=5)
    assert in_code.base_dir is None
    assert in_code.resolve_path("pick.bddl") == Path("pick.bddl")
