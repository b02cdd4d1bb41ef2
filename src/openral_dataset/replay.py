"""``lookup_frame``: one row of a recording, the tick it came from, and the camera frames it shows.

``openral replay --frame DIR/EPISODE/FRAME`` prints the row (state, requested and sent action,
timings, capture stamps, trace and span id, so the tick can be found in a tracing backend) and
writes the decoded camera frames to image files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from openral_core import ROSConfigError, ROSDependencyMissing
from openral_dataset import layout, meta_reader, schema

try:
    import av
    import pyarrow.parquet as pq
except ImportError as exc:
    raise ROSDependencyMissing(exc.name or "av", extra="dataset", needed_for="replaying datasets") from exc

TIME_TOLERANCE_S = 1e-4


@dataclass(frozen=True)
class ReplayFrame:
    """One dataset row and the decoded picture (RGB, ``[H, W, 3]``) of each camera at that row."""

    episode_idx: int
    frame_idx: int
    row: dict[str, Any]
    images: dict[str, np.ndarray]


def parse_frame_path(text: str) -> tuple[Path, int, int]:
    """``DIR/EPISODE/FRAME`` → (dataset folder, episode index, frame index).

    Raises:
        ROSConfigError: The last two parts are not whole numbers.
    """
    path = Path(text)
    try:
        return path.parent.parent, int(path.parent.name), int(path.name)
    except ValueError:
        raise ROSConfigError(
            f"'{text}' is not DIR/EPISODE/FRAME", field="--frame", hint="e.g. data/wave/0/42: episode 0, frame 42"
        ) from None


def lookup_frame(root: Path, episode_idx: int, frame_idx: int) -> ReplayFrame:
    """The row ``frame_idx`` of episode ``episode_idx`` and its camera frames.

    Raises:
        ROSConfigError: No such dataset, episode or frame.
    """
    try:
        info = meta_reader.read_meta(root)
    except meta_reader.MetaError as exc:
        raise ROSConfigError(
            f"{root}: {exc}", field="--frame", hint=f"openral dataset check {root} lists every problem"
        ) from None
    if info is None:
        raise ROSConfigError(f"{root} is not a dataset (no meta/info.json)", field="--frame")
    episodes = info.total_episodes
    if not 0 <= episode_idx < episodes:
        raise ROSConfigError(
            f"episode {episode_idx} does not exist; the dataset has 0..{episodes - 1}", field="--frame"
        )
    table = pq.read_table(layout.data_file(root, episode_idx))
    if not 0 <= frame_idx < table.num_rows:
        raise ROSConfigError(
            f"frame {frame_idx} does not exist; episode {episode_idx} has 0..{table.num_rows - 1}", field="--frame"
        )
    row = {name: values[0] for name, values in table.slice(frame_idx, 1).to_pydict().items()}
    images = {}
    for key in info.video_keys:  # checked: each is one safe folder name, so the camera is a safe file name too
        camera = key.removeprefix(schema.IMAGE_PREFIX)
        images[camera] = _decode_at(layout.video_file(root, key, episode_idx), frame_idx / info.fps)
    return ReplayFrame(episode_idx, frame_idx, row, images)


def _decode_at(path: Path, seconds: float) -> np.ndarray:
    """The picture shown at ``seconds`` (within LeRobot's 1e-4 s tolerance)."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        base = stream.time_base
        if base is None:
            raise ROSConfigError(f"{path}: the video stream has no time base")
        container.seek(math.floor(seconds / base), stream=stream, backward=True)
        for frame in container.decode(stream):
            if frame.pts is None:
                continue
            at = float(frame.pts * base)
            if abs(at - seconds) <= TIME_TOLERANCE_S:
                picture: np.ndarray = frame.to_ndarray(format="rgb24")
                return picture
            if at > seconds:
                break
    raise ROSConfigError(f"{path}: no frame at {seconds:.6f} s")
