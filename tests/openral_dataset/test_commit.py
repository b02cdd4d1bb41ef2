"""The commit journal: after an interrupted commit, only files whose identity proves them the recorder's are removed."""

from __future__ import annotations

from pathlib import Path

import pytest

from openral_dataset import commit, layout


class _Killed(BaseException):
    """The process dying part-way."""


def _stage(folder: Path, name: str, data: bytes) -> Path:
    path = folder / name
    layout.write_file(path, data)
    return path


def _interrupted(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, *, moves_done: int) -> tuple[Path, Path]:
    """A dataset of one episode whose commit of episode 1 died after ``moves_done`` of its three renames."""
    root = tmp_path / "ds"
    (root / "meta").mkdir(parents=True)
    (root / layout.TASKS_PATH).write_bytes(b"tasks of episode 0")
    (root / layout.INFO_PATH).write_bytes(b"info of episode 0")
    folder = root / layout.STAGING_DIR / "episode-000001"
    moves = [
        commit.Move(_stage(folder, "data.parquet", b"rows of 1"), layout.data_file(root, 1)),
        commit.Move(_stage(folder, "tasks", b"tasks of 0 and 1"), root / layout.TASKS_PATH, replaces=True),
        commit.Move(_stage(folder, "info", b"info of 0 and 1"), root / layout.INFO_PATH, replaces=True),
    ]
    real = layout.move_synced
    done = iter(range(moves_done + 1))

    def dying(src: Path, dst: Path) -> None:
        if next(done) == moves_done:
            raise _Killed
        real(src, dst)

    monkeypatch.setattr(layout, "move_synced", dying)
    if moves_done < len(moves):
        with pytest.raises(_Killed):
            commit.apply(root, folder, 1, moves)
    else:  # every rename done; the staging folder not yet removed
        commit.apply(root, folder, 1, moves)
    monkeypatch.undo()
    return root, folder


def test_recovery_puts_the_replaced_metadata_back_and_removes_the_moved_episode_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root, _ = _interrupted(tmp_path, monkeypatch, moves_done=2)
    assert (root / layout.TASKS_PATH).read_bytes() == b"tasks of 0 and 1"

    removed = commit.recover(root, committed=1)
    assert sorted(p.relative_to(root).as_posix() for p in removed) == [
        "data/chunk-000/file-001.parquet",
        layout.TASKS_PATH,
    ]
    assert (root / layout.TASKS_PATH).read_bytes() == b"tasks of episode 0"
    assert (root / layout.INFO_PATH).read_bytes() == b"info of episode 0"
    assert not layout.data_file(root, 1).exists()
    assert not (root / layout.STAGING_DIR).exists()


def test_recovery_leaves_a_file_that_took_the_place_of_the_recorders(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root, _ = _interrupted(tmp_path, monkeypatch, moves_done=2)
    # After the crash someone puts their own files where the recorder's were.
    layout.data_file(root, 1).unlink()
    layout.data_file(root, 1).write_bytes(b"rows of 1")  # same name, same bytes, another file
    (root / layout.TASKS_PATH).unlink()
    (root / layout.TASKS_PATH).write_bytes(b"edited by hand")

    assert commit.recover(root, committed=1) == []
    assert layout.data_file(root, 1).read_bytes() == b"rows of 1"
    assert (root / layout.TASKS_PATH).read_bytes() == b"edited by hand"


def test_a_commit_whose_info_json_is_in_place_is_never_undone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root, folder = _interrupted(tmp_path, monkeypatch, moves_done=3)  # died after the last rename, before cleanup
    assert (root / layout.INFO_PATH).read_bytes() == b"info of 0 and 1"
    assert commit.recover(root, committed=1) == []  # a stale count: info.json itself proves the commit
    assert layout.data_file(root, 1).read_bytes() == b"rows of 1"
    assert (root / layout.TASKS_PATH).read_bytes() == b"tasks of 0 and 1"
    assert not folder.exists()
