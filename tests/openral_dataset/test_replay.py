"""Replay and every other place a feature name becomes a path: a name that leaves its folder is refused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from openral_cli.main import cli
from openral_core import FrameEncoding, ROSConfigError, SensorFrame
from openral_dataset import layout, schema
from openral_dataset.check import check_dataset
from openral_dataset.writer import LeRobotDatasetSink

W, H = 32, 24


def _sink(root: Path, camera: str, *, resume: bool = False) -> LeRobotDatasetSink:
    return LeRobotDatasetSink(
        root,
        fps=30,
        robot_type="test_arm",
        joint_names=["a", "b"],
        cameras=[schema.CameraSpec(camera, W, H)],
        vcodec="h264",
        resume=resume,
    )


@pytest.fixture
def one_episode(tmp_path: Path) -> Path:
    root = tmp_path / "ds"
    sink = _sink(root, "cam")
    sink.begin_episode("look")
    for k in range(3):
        frame = SensorFrame(
            sensor_id="cam",
            stamp_ns=k,
            width=W,
            height=H,
            encoding=FrameEncoding.RGB8,
            seq=k,
            data=np.full((H, W, 3), 60 * k, np.uint8),
        )
        sink.add_row({schema.STATE: [0.0, 0.0], schema.ACTION: [0.0, 0.0]}, {"cam": frame})
    sink.end_episode(success=True)
    sink.close()
    return root


def _rename_camera(root: Path, key: str) -> None:
    """Give the camera feature ``key`` and put its video where a naive ``videos/<key>/…`` join resolves."""
    path = root / layout.INFO_PATH
    info = json.loads(path.read_text())
    info["features"] = {(key if k == "observation.images.cam" else k): v for k, v in info["features"].items()}
    path.write_text(json.dumps(info))
    (root / "videos" / key.split("/", maxsplit=1)[0]).mkdir(parents=True, exist_ok=True)  # for ".." to resolve
    target = root / layout.VIDEO_PATH.format(video_key=key, chunk_index=0, file_index=0)
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(layout.video_file(root, "observation.images.cam", 0), target)


@pytest.mark.parametrize("camera", ["../../escaped", "/ABSOLUTE/escaped", "..\\..\\escaped"])
def test_replay_writes_nothing_outside_out_for_a_feature_name_that_leaves_its_folder(
    one_episode: Path, tmp_path: Path, camera: str
) -> None:
    camera = camera.replace("/ABSOLUTE", str(tmp_path / "elsewhere"))
    (tmp_path / "elsewhere").mkdir()
    _rename_camera(one_episode, schema.IMAGE_PREFIX + camera)
    out = tmp_path / "a" / "b" / "out"

    result = CliRunner().invoke(cli, ["replay", "--frame", f"{one_episode}/0/1", "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert "cannot name a folder or file" in result.output
    assert list(tmp_path.rglob("*.png")) == []


def test_check_and_resume_refuse_a_feature_name_that_leaves_its_folder(one_episode: Path) -> None:
    _rename_camera(one_episode, schema.IMAGE_PREFIX + "../../escaped")
    problems = check_dataset(one_episode).problems
    assert len(problems) == 1
    assert "meta/info.json: feature 'observation.images.../../escaped'" in problems[0]
    with pytest.raises(ROSConfigError, match="cannot name a folder or file"):
        _sink(one_episode, "cam", resume=True)


def test_a_camera_whose_name_would_leave_the_video_folder_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match=r"sensors\[\].sensor_id: camera '\.\./x' cannot name a video folder"):
        _sink(tmp_path / "ds", "../x")
    with pytest.raises(ROSConfigError, match="cannot name a video folder"):
        layout.video_file(tmp_path, "..", 0)
    assert not (tmp_path / "ds").exists()
