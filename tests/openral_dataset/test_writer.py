"""The dataset files themselves: what LeRobot's loader and its training collation need of every row and episode."""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from openral_core import FrameEncoding, ROSConfigError, ROSRuntimeError, SensorFrame
from openral_dataset import layout, schema
from openral_dataset.check import check_dataset
from openral_dataset.writer import LeRobotDatasetSink

JOINTS = ["a", "b"]
W, H = 32, 24


def _frame(sensor_id: str, encoding: FrameEncoding, pixels: np.ndarray, seq: int) -> SensorFrame:
    return SensorFrame(
        sensor_id=sensor_id,
        stamp_ns=seq * 1_000_000,
        width=W,
        height=H,
        encoding=encoding,
        seq=seq,
        data=np.ascontiguousarray(pixels),
    )


def _sink(
    root: Path, cameras: list[schema.CameraSpec], *, vcodec: str = "h264", resume: bool = False
) -> LeRobotDatasetSink:
    return LeRobotDatasetSink(
        root, fps=30, robot_type="test_arm", joint_names=JOINTS, cameras=cameras, vcodec=vcodec, resume=resume
    )


def _row(k: int, **extra: object) -> dict[str, object]:
    return {schema.STATE: [0.1 * k, 0.0], schema.ACTION: [0.1 * k, 0.5], **extra}


def test_rows_without_a_value_hold_typed_placeholders_never_nulls(tmp_path: Path) -> None:
    sink = _sink(tmp_path / "ds", [schema.CameraSpec("cam", W, H)])
    sink.begin_episode("pick")
    grey = np.full((H, W, 3), 90, np.uint8)
    # Tick 0: no camera frame yet, the action withheld, the tick untraced.
    sink.add_row(_row(0, **{schema.ACTION_APPLIED: False, schema.WITHHELD_REASON: "stale_sensor"}), {"cam": None})
    for k in range(1, 4):
        frame = _frame("cam", FrameEncoding.RGB8, grey, k)
        row = _row(k, **{schema.ACTION_APPLIED: True, schema.REQUESTED_ACTION: [0.1 * k, 0.5]})
        row[schema.camera_column("cam", "seq")] = k
        sink.add_row(row, {"cam": frame})
    sink.end_episode(success=True)
    sink.close()

    table = pq.read_table(layout.data_file(tmp_path / "ds", 0))
    assert {c: table.column(c).null_count for c in table.column_names if table.column(c).null_count} == {}
    rows = table.to_pydict()
    assert rows[schema.WITHHELD_REASON] == ["stale_sensor", "", "", ""]
    assert rows[schema.TRACE_ID] == [""] * 4
    assert rows[schema.camera_column("cam", "seq")] == [-1, 1, 2, 3]
    assert all(math.isnan(v) for v in rows[schema.REQUESTED_ACTION][0])
    assert math.isnan(rows[schema.camera_column("cam", "age_ms")][0])
    assert check_dataset(tmp_path / "ds").problems == []


def test_episode_metadata_has_one_schema_whatever_the_outcome(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    sink = _sink(root, [schema.CameraSpec("cam", W, H)])
    for outcome in (None, True, False):
        sink.begin_episode("pick")
        for k in range(3):
            sink.add_row(_row(k), {"cam": None})  # a camera that never delivers: black filler frames
        sink.end_episode(success=outcome)
    sink.close()

    tables = [pq.read_table(layout.episodes_file(root, e)) for e in range(3)]
    first = tables[0].schema.remove_metadata()
    assert all(t.schema.remove_metadata().equals(first) for t in tables)
    merged = pa.concat_tables(tables)  # what LeRobot does with them
    # Exactly LeRobot's columns (it appends only to such rows): statistics of every non-text
    # feature, nothing of openral's own; the outcome lives beside them.
    stats_of = {c.split("/")[1] for c in merged.column_names if c.startswith("stats/")}
    assert stats_of == {name for name, spec in sink.features.items() if spec["dtype"] != "string"}
    assert not [c for c in merged.column_names if c.startswith("openral.")]
    outcomes = [json.loads(line) for line in (root / layout.OUTCOMES_PATH).read_text().splitlines()]
    assert [o["success"] for o in outcomes] == [None, True, False]
    image_mean = merged.column("stats/observation.images.cam/mean").to_pylist()
    assert image_mean == [[[[0.0]], [[0.0]], [[0.0]]]] * 3
    assert check_dataset(root).problems == []


def test_camera_stats_are_per_rgb_channel_for_grey_and_bgr_cameras(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    sink = _sink(root, [schema.CameraSpec("mono", W, H), schema.CameraSpec("bgr", W, H)])
    sink.begin_episode("look")
    bgr = np.zeros((H, W, 3), np.uint8)
    bgr[..., 0] = 255  # blue in BGR order
    for k in range(4):
        frames = {
            "mono": _frame("mono", FrameEncoding.MONO8, np.full((H, W), 51, np.uint8), k),
            "bgr": _frame("bgr", FrameEncoding.BGR8, bgr, k),
        }
        sink.add_row(_row(k), frames)
    sink.end_episode(success=True)
    sink.close()

    meta = pq.read_table(layout.episodes_file(root, 0)).to_pylist()[0]
    mono = np.asarray(meta["stats/observation.images.mono/mean"]).ravel()
    np.testing.assert_allclose(mono, [0.2, 0.2, 0.2], atol=1e-6)
    blue = np.asarray(meta["stats/observation.images.bgr/mean"]).ravel()
    np.testing.assert_allclose(blue, [0.0, 0.0, 1.0], atol=1e-6)  # R, G, B as the video decodes
    assert check_dataset(root).problems == []


def test_resume_refuses_a_different_video_codec(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    sink = _sink(root, [schema.CameraSpec("cam", W, H)])
    sink.begin_episode("pick")
    sink.add_row(_row(0), {"cam": None})
    sink.end_episode(success=True)
    sink.close()
    with pytest.raises(ROSConfigError, match=r"changed \['observation.images.cam'\]"):
        _sink(root, [schema.CameraSpec("cam", W, H)], vcodec="libsvtav1", resume=True)


def test_check_names_nulls_and_episode_schemas_that_differ(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    sink = _sink(root, [])
    for _ in range(2):
        sink.begin_episode("pick")
        sink.add_row(_row(0), {})
        sink.end_episode(success=True)
    sink.close()
    data = layout.data_file(root, 1)
    table = pq.read_table(data)
    column = table.schema.get_field_index(schema.TRACE_ID)
    pq.write_table(table.set_column(column, schema.TRACE_ID, pa.array([None], pa.string())), data)
    meta = layout.episodes_file(root, 1)
    episode = pq.read_table(meta)
    pq.write_table(episode.drop_columns(["stats/openral.tick_idx/min"]), meta)

    problems = check_dataset(root).problems
    assert any("null values {'openral.trace_id': 1}" in p for p in problems)
    assert any("schema differs from episode 0's" in p for p in problems)


# -- opening: refuse before touching a file -------------------------------------------------------


def _snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` but the staging area, with its bytes."""
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and layout.STAGING_DIR not in p.parts
    }


def _record(sink: LeRobotDatasetSink, rows: int, task: str = "pick") -> None:
    sink.begin_episode(task)
    for k in range(rows):
        sink.add_row(_row(k), {"cam": None} if sink.cameras else {})
    sink.end_episode(success=True)


@pytest.fixture
def two_episodes(tmp_path: Path) -> Path:
    """A two-episode dataset without cameras (3 and 4 rows)."""
    root = tmp_path / "ds"
    sink = _sink(root, [])
    _record(sink, 3)
    _record(sink, 4, "place")
    sink.close()
    return root


@pytest.mark.parametrize("resume", [False, True])
def test_a_folder_that_never_was_a_dataset_is_refused_and_nothing_is_deleted(tmp_path: Path, resume: bool) -> None:
    root = tmp_path / "proj"
    (root / "data" / "chunk-000").mkdir(parents=True)
    (root / "data" / "measurements.csv").write_text("t,x\n")
    (root / "data" / "chunk-000" / "file-000.parquet").write_bytes(b"named like a dataset's file, but mine")
    (root / "videos" / "holiday").mkdir(parents=True)
    (root / "videos" / "holiday" / "beach.mp4").write_bytes(b"x")
    before = _snapshot(root)

    with pytest.raises(ROSConfigError) as refused:
        _sink(root, [], resume=resume)
    message = str(refused.value)
    assert "is not an openral dataset" in message
    assert "data/measurements.csv" in message
    assert "--resume" not in message  # the hint invites no deletion
    assert "clean" not in message
    assert _snapshot(root) == before


def _set_info(root: Path, **changes: object) -> None:
    path = root / layout.INFO_PATH
    info = json.loads(path.read_text())
    info.update(changes)
    path.write_text(json.dumps(info))


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({"total_episodes": -1}, "meta/info.json: total_episodes must be a whole number >= 0, got -1"),
        ({"total_episodes": 0.5}, "meta/info.json: total_episodes must be a whole number >= 0, got 0.5"),
        ({"total_episodes": True}, "meta/info.json: total_episodes must be a whole number >= 0, got true"),
        ({"total_episodes": "2"}, 'meta/info.json: total_episodes must be a whole number >= 0, got "2"'),
        ({"total_frames": -7}, "meta/info.json: total_frames must be a whole number >= 0, got -7"),
        ({"fps": 0}, "meta/info.json: fps must be a whole number >= 1, got 0"),
        # Counters that parse but disagree with meta/episodes/.
        ({"total_episodes": 1, "splits": {"train": "0:1"}}, "data/chunk-000/file-001.parquet: orphan"),
        ({"total_episodes": 3, "splits": {"train": "0:3"}}, "total_episodes 3, but meta/episodes/ holds 2"),
        ({"total_frames": 8}, "meta/info.json: total_frames 8, the episodes in meta/episodes/ hold 7"),
        ({"total_tasks": 1}, "meta/tasks.parquet: 2 task(s), info.json says 1"),
    ],
)
def test_resume_refuses_counters_it_cannot_trust_before_touching_a_file(
    two_episodes: Path, changes: dict[str, object], expected: str
) -> None:
    _set_info(two_episodes, **changes)
    before = _snapshot(two_episodes)
    with pytest.raises(ROSConfigError, match="--dataset-out") as refused:
        _sink(two_episodes, [], resume=True)
    assert expected in str(refused.value)
    assert "\n" not in str(refused.value)
    assert _snapshot(two_episodes) == before


@pytest.mark.parametrize(
    ("path", "content", "expected"),
    [
        (layout.INFO_PATH, b'{"codebase_version": "v3', "meta/info.json: not valid JSON"),
        (layout.INFO_PATH, b"", "meta/info.json: not valid JSON"),
        (layout.INFO_PATH, b"\x00\xff\xfe\x89PNG", "meta/info.json: not valid JSON"),
        (layout.INFO_PATH, b"[1, 2]", "meta/info.json: holds a JSON array, not an object"),
        (layout.INFO_PATH, b"42", "meta/info.json: holds a JSON number, not an object"),
        (layout.TASKS_PATH, None, "meta/tasks.parquet: unreadable"),
        (layout.STATS_PATH, b'{"observation.state": {"mean": [1, 2', "meta/stats.json: not valid JSON"),
        (layout.STATS_PATH, b'{"action": {"mean": ["a"]}}', "meta/stats.json: action.mean is not an array of numbers"),
        (layout.OUTCOMES_PATH, b'{"episode_index": 0}\n{"episo', "meta/openral_episodes.jsonl: line 2"),
        ("meta/episodes/chunk-000/file-001.parquet", None, "meta/episodes/chunk-000/file-001.parquet: unreadable"),
    ],
)
def test_resume_refuses_damaged_metadata_naming_the_file_and_deletes_nothing(
    two_episodes: Path, path: str, content: bytes | None, expected: str
) -> None:
    target = two_episodes / path
    target.write_bytes(target.read_bytes()[:40] if content is None else content)  # None: truncated
    before = _snapshot(two_episodes)
    with pytest.raises(ROSConfigError) as refused:
        _sink(two_episodes, [], resume=True)
    assert expected in str(refused.value)
    assert "\n" not in str(refused.value)
    assert _snapshot(two_episodes) == before
    assert any(expected in p for p in check_dataset(two_episodes).problems)  # the check flags the same


def test_resume_refuses_a_file_it_did_not_write_where_its_next_episode_goes(two_episodes: Path) -> None:
    stray = layout.data_file(two_episodes, 2)
    stray.write_bytes(b"someone else's")
    with pytest.raises(ROSConfigError, match=r"data/chunk-000/file-002.parquet: orphan"):
        _sink(two_episodes, [], resume=True)
    assert stray.read_bytes() == b"someone else's"


def test_a_folder_that_cannot_be_written_is_refused_before_the_first_episode(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Tests run as root, whom a read-only mode does not stop: the file system refuses instead.
    def read_only(path: Path, data: bytes) -> None:
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))

    monkeypatch.setattr(layout, "write_file", read_only)
    with pytest.raises(ROSConfigError, match=r"--dataset-out: cannot write into .*ds: Read-only file system"):
        _sink(tmp_path / "ds", [])
    monkeypatch.undo()
    (tmp_path / "a-file").write_text("")
    with pytest.raises(ROSConfigError, match="cannot write into"):
        _sink(tmp_path / "a-file" / "ds", [])


# -- committing: a failed or interrupted commit leaves the dataset as it was -----------------------


class _Disk:
    """Counts every ``fsync`` and rename; the ``fail_at``-th raises ENOSPC before or after it happens.

    A full disk shows as an error on writing or syncing; a test running as root cannot fill one.
    """

    def __init__(self, monkeypatch: pytest.MonkeyPatch, error: type[BaseException] = OSError) -> None:
        self.ops = 0
        self.fail_at: int | None = None
        self.after = False
        self.error = error
        for name in ("fsync", "replace"):
            real = getattr(os, name)
            monkeypatch.setattr(os, name, lambda *a, _real=real, **kw: self._do(_real, *a, **kw))

    def _do(self, op: Any, *args: Any, **kwargs: Any) -> None:
        self.ops += 1
        failing = self.ops == self.fail_at
        if failing and not self.after:
            raise self.error(errno.ENOSPC, os.strerror(errno.ENOSPC))
        op(*args, **kwargs)
        if failing:
            raise self.error(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _ops_of_one_commit(disk: _Disk, sink: LeRobotDatasetSink) -> int:
    sink.begin_episode("count")
    sink.add_row(_row(0), {"cam": None})
    start = disk.ops
    sink.end_episode(success=True)
    return disk.ops - start


@pytest.mark.parametrize("first", [True, False], ids=["first-episode", "third-episode"])
@pytest.mark.parametrize("after", [False, True], ids=["before-the-write", "after-the-write"])
def test_a_commit_that_fails_at_any_write_leaves_the_dataset_as_it_was(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, first: bool, after: bool
) -> None:
    disk = _Disk(monkeypatch)
    probe = _sink(tmp_path / "probe", [schema.CameraSpec("cam", W, H)])
    ops = _ops_of_one_commit(disk, probe)
    probe.close()
    assert ops >= 10  # data, episode row, four metadata files, the journal; their moves
    episode = 0 if first else 2

    root = tmp_path / "ds"
    sink = _sink(root, [schema.CameraSpec("cam", W, H)])
    if not first:
        _record(sink, 3)
        _record(sink, 2, "place")
    before = _snapshot(root)
    disk.after = after
    committed_at = None
    for k in range(1, ops + 1):
        sink.begin_episode("doomed")
        for row in range(4):
            sink.add_row(_row(row), {"cam": None})
        disk.fail_at = disk.ops + k
        try:
            sink.end_episode(success=True)
        except ROSRuntimeError as exc:
            failure = str(exc)
        else:
            committed_at = k
            break
        assert f"cannot write episode {episode} into {root}: No space left on device" in failure
        assert _snapshot(root) == before, f"failure at operation {k} of {ops}"
        assert not list((root / layout.STAGING_DIR).iterdir())
    # Only a failure once info.json is in place (syncing its folder) leaves the episode committed.
    assert committed_at is not None
    assert committed_at >= ops - 1
    disk.fail_at = None
    _record(sink, 2, "after the disk was freed")
    sink.close()
    report = check_dataset(root)
    assert report.problems == []
    assert report.episodes == (2 if first else 4)


class _Killed(BaseException):
    """The process dying part-way: nothing of the recorder runs after it."""


def test_a_commit_interrupted_at_any_point_is_undone_when_the_dataset_is_opened(
    two_episodes: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    disk = _Disk(monkeypatch, error=_Killed)
    scratch = tmp_path / "scratch"
    shutil.copytree(two_episodes, scratch)
    ops = _ops_of_one_commit(disk, _sink(scratch, [], resume=True))
    before = _snapshot(two_episodes)
    for k in range(1, ops):  # the last operation is the commit itself
        root = tmp_path / f"killed-at-{k}"
        shutil.copytree(two_episodes, root)
        sink = _sink(root, [], resume=True)
        sink.begin_episode("killed")
        sink.add_row(_row(0), {})
        disk.fail_at = disk.ops + k
        with pytest.raises(_Killed):
            sink.end_episode(success=True)
        disk.fail_at = None
        (root / "notes.txt").write_text("mine")  # a file of the user's beside the dataset

        reopened = _sink(root, [], resume=True)
        assert reopened.total_episodes == 2
        assert _snapshot(root) == {**before, "notes.txt": b"mine"}, f"killed at operation {k}"
        reopened.close()
        assert check_dataset(root).problems == []


def test_a_sink_built_to_open_later_touches_nothing_until_open(tmp_path: Path) -> None:
    root = tmp_path / "later" / "ds"
    sink = LeRobotDatasetSink(root, fps=30, robot_type="test_arm", joint_names=JOINTS, defer_open=True)
    assert not sink.is_open
    with pytest.raises(ROSRuntimeError, match="not opened"):
        sink.begin_episode("pick")
    sink.close()
    assert not (tmp_path / "later").exists()
    sink.open()
    sink.open()  # idempotent
    sink.begin_episode("pick")
    sink.add_row(_row(0), {})
    sink.end_episode(success=True)
    sink.close()
    assert check_dataset(root).problems == []
