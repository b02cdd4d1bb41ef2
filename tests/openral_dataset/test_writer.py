"""The dataset files themselves: what LeRobot's loader and its training collation need of every row and episode."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from openral_core import FrameEncoding, ROSConfigError, SensorFrame
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
