"""``LeRobotDatasetSink``: episodes written as LeRobotDataset v3.0 with pyarrow and PyAV, each committed atomically.

An episode is built in a staging folder outside ``data/``, ``meta/`` and ``videos/``: its rows in
memory, one streaming video encoder per camera (frames are encoded while recording). Committing
writes and syncs its data and episode parquet files and the dataset's new ``tasks.parquet``,
``stats.json``, outcome lines and ``info.json`` there, then moves them into place, ``info.json``
last (:mod:`openral_dataset.commit`): until that rename the episode does not exist. A failed
commit is put back at once; one a crash interrupted, the next time the dataset is opened.

Opening refuses what it cannot trust before it touches a file: a folder holding files that are
not an openral dataset, metadata that ``openral dataset check`` would flag
(:mod:`openral_dataset.meta`), a folder it cannot write.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from openral_core import FrameEncoding, ROSConfigError, ROSDependencyMissing, ROSRuntimeError, SensorFrame
from openral_dataset import commit, layout, meta, schema, stats
from openral_dataset.meta import read_tasks
from openral_dataset.video import EncoderProcess, OverflowPolicy, StreamingVideoEncoder

try:
    import pyarrow as pa
    import pyarrow.parquet as pq
except ImportError as exc:
    raise ROSDependencyMissing("pyarrow", extra="dataset", needed_for="recording datasets") from exc

_log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class EpisodeSummary:
    """What one committed (or discarded) episode held."""

    episode_idx: int
    frames: int
    task: str
    committed: bool
    repeated_frames: dict[str, int]
    close_s: float = 0.0


@dataclass
class _Episode:
    idx: int
    task: str
    task_index: int
    folder: Path
    rows: dict[str, list[Any]]
    encoders: dict[str, StreamingVideoEncoder] = field(default_factory=dict)
    samples: dict[str, list[np.ndarray]] = field(default_factory=dict)
    sample_stride: dict[str, int] = field(default_factory=dict)
    unsized: dict[str, int] = field(default_factory=dict)
    failed: bool = False
    long_warned: bool = False


class LeRobotDatasetSink:
    """Writes episodes of one robot and its cameras into a LeRobotDataset v3.0 folder.

    Args:
        root: The dataset folder (created if missing).
        fps: Frames per second: the recording's tick rate, an integer.
        robot_type: Recorded in ``info.json``.
        joint_names: Names of the state vector (and of the action, unless ``action_names``), from
            the robot manifest.
        action_names: Names of the action vector when it is not joint positions (a simulator's
            action space).
        environment_state_names: Names of a simulator's object state, recorded as
            ``observation.environment_state``.
        cameras: Recorded cameras with their video size (0 x 0: the size of the camera's first frame).
        vcodec: ``libsvtav1`` (default) or ``h264``.
        overflow: What happens when a camera's encoder falls behind.
        resume: Append to an existing dataset (its features must match); otherwise an existing,
            non-empty dataset is refused.

    Raises:
        ROSConfigError: A bad rate, codec or camera name; an existing dataset without ``resume``,
            or one whose metadata is damaged or whose features differ from this recording's; a
            folder holding other files; a folder that cannot be written.
    """

    def __init__(
        self,
        root: Path,
        *,
        fps: int,
        robot_type: str,
        joint_names: Sequence[str],
        action_names: Sequence[str] | None = None,
        environment_state_names: Sequence[str] = (),
        cameras: Sequence[schema.CameraSpec] = (),
        vcodec: str = "libsvtav1",
        overflow: OverflowPolicy = OverflowPolicy.REPEAT,
        resume: bool = False,
    ) -> None:
        if fps < 1:
            raise ROSConfigError(f"must be a whole number of frames per second >= 1, got {fps}", field="fps")
        self.root = root
        self.fps = fps
        self.robot_type = robot_type
        self.joint_names = list(joint_names)
        self.action_names = self.joint_names if action_names is None else list(action_names)
        self.environment_state_names = list(environment_state_names)
        self.cameras = list(cameras)
        for cam in self.cameras:
            why = layout.unsafe_key(schema.video_key(cam.sensor_id))
            if why is not None:
                raise ROSConfigError(
                    f"camera {cam.sensor_id!r} cannot name a video folder: {why}", field="sensors[].sensor_id"
                )
        self.vcodec = vcodec
        self.overflow = OverflowPolicy(overflow)
        self.features = self._features()
        self._arrow = schema.arrow_schema(self.features)
        self._absent = schema.absent_values(self.features)
        self._episode: _Episode | None = None
        self._processes: dict[str, EncoderProcess] = {}
        self._tasks: dict[str, int] = {}
        self._stats: list[dict[str, dict[str, np.ndarray]]] = []
        self._merged: dict[str, dict[str, np.ndarray]] = {}
        self._outcomes: list[str] = []
        self.total_episodes = 0
        self.total_frames = 0
        self._open(resume)

    def _features(self) -> dict[str, dict[str, Any]]:
        return schema.features(
            self.joint_names,
            self.cameras,
            fps=self.fps,
            vcodec=self.vcodec,
            action_names=self.action_names,
            environment_state_names=self.environment_state_names,
        )

    # -- opening ---------------------------------------------------------------------------

    def _open(self, resume: bool) -> None:
        if self.root.exists() and not self.root.is_dir():
            raise ROSConfigError(f"{self.root} is a file, not a folder", field="--dataset-out")
        try:
            found = meta.read_meta(self.root)
        except meta.MetaError as exc:
            raise ROSConfigError(
                f"cannot open {self.root}: {exc}",
                field="--dataset-out",
                hint=f"repair or restore that file, or record into another folder; "
                f"openral dataset check {self.root} lists every problem",
            ) from None
        if found is None:
            self._open_new()
            return
        if not resume:
            raise ROSConfigError(
                f"{self.root} already holds a dataset of {found.total_episodes} episode(s)",
                field="--dataset-out",
                hint="pass --resume to add episodes to it, or choose another folder",
            )
        self._adopt_sizes(found.features)
        self._check_compatible(found)
        with self._writing():
            self._report_cleanup(commit.recover(self.root, found.total_episodes))
        problems = meta.meta_problems(self.root, found)
        if problems:
            more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
            raise ROSConfigError(
                f"cannot resume {self.root}: {problems[0]}{more}",
                field="--dataset-out",
                hint=f"repair or restore those files, or record into another folder; "
                f"openral dataset check {self.root} lists every problem",
            )
        self.total_episodes = found.total_episodes
        self.total_frames = found.total_frames
        self._tasks = read_tasks(self.root)
        self._outcomes = meta.read_outcome_lines(self.root, self.total_episodes)
        self._merged = meta.read_stats(self.root) or {}
        self._check_writable()

    def _open_new(self) -> None:
        """No ``info.json``: an interrupted first episode of ours is put back; any other file is refused."""
        with self._writing():
            self._report_cleanup(commit.recover(self.root, 0))
        foreign = layout.foreign_files(self.root)
        if foreign:
            listed = ", ".join(str(p.relative_to(self.root)) for p in foreign[:3])
            if len(foreign) > 3:
                listed += f" and {len(foreign) - 3} more"
            raise ROSConfigError(
                f"{self.root} is not an openral dataset: it has no {layout.INFO_PATH} but holds {listed}",
                field="--dataset-out",
                hint="record into an empty or new folder; openral never deletes files it did not write",
            )
        self._check_writable()

    def _check_writable(self) -> None:
        """Prove the folder takes a synced file now, before the first tick rather than at the first commit."""
        with self._writing():
            layout.check_writable(self.root)

    @contextlib.contextmanager
    def _writing(self) -> Iterator[None]:
        try:
            yield
        except OSError as exc:
            raise ROSConfigError(
                f"cannot write into {self.root}: {exc.strerror or exc}",
                field="--dataset-out",
                hint="choose a folder you can write to, on a disk with room",
            ) from exc

    def _adopt_sizes(self, features: dict[str, dict[str, Any]]) -> None:
        """Cameras whose size was left open take the size the dataset already has."""
        for index, cam in enumerate(self.cameras):
            spec = features.get(schema.video_key(cam.sensor_id))
            if not cam.width and spec is not None and spec["dtype"] == "video":
                height, width, _channels = spec["shape"]
                self.cameras[index] = schema.CameraSpec(cam.sensor_id, width, height)
        self.features = self._features()

    def _check_compatible(self, found: meta.DatasetMeta) -> None:
        problems = []
        if found.fps != self.fps:
            problems.append(f"fps {found.fps} (this recording: {self.fps})")
        theirs = {k: _signature(v) for k, v in found.features.items()}
        ours = {k: _signature(v) for k, v in self.features.items()}
        if theirs != ours:
            missing = sorted(set(ours) - set(theirs))
            extra = sorted(set(theirs) - set(ours))
            changed = sorted(k for k in set(ours) & set(theirs) if ours[k] != theirs[k])
            problems.append(f"features differ (missing {missing}, extra {extra}, changed {changed})")
        if problems:
            raise ROSConfigError(
                f"cannot resume {self.root}: " + "; ".join(problems),
                field="--dataset-out",
                hint="record into a new folder, or use the robot, cameras and rate the dataset was recorded with",
            )

    def _report_cleanup(self, removed: list[Path]) -> None:
        if removed:
            _log.warning(
                "removed files of an episode that was never committed",
                dataset=str(self.root),
                files=[str(p.relative_to(self.root)) for p in removed],
            )

    # -- episodes --------------------------------------------------------------------------

    @property
    def episode_open(self) -> bool:
        return self._episode is not None

    def begin_episode(self, task: str) -> int:
        """Start the next episode; returns its index.

        Raises:
            ROSRuntimeError: An episode is already open.
        """
        if self._episode is not None:
            raise ROSRuntimeError(f"episode {self._episode.idx} is still open")
        idx = self.total_episodes
        task_index = self._tasks.get(task, len(self._tasks))
        folder = self.root / layout.STAGING_DIR / f"episode-{idx:06d}"
        try:
            if folder.exists():
                commit.discard(self.root, folder, committed=self.total_episodes)
            folder.mkdir(parents=True)
        except OSError as exc:
            raise ROSRuntimeError(f"cannot write into {self.root}: {exc.strerror or exc}") from exc
        self._episode = _Episode(idx, task, task_index, folder, {name: [] for name in self._arrow.names})
        return idx

    def add_row(self, row: dict[str, Any], frames: Mapping[str, SensorFrame | None]) -> None:
        """Append one row (the ``openral.*`` values and state/action) and each camera's frame for it.

        A camera missing from ``frames`` (or ``None``) repeats its previous frame, and the row says so.

        Raises:
            ROSRuntimeError: No episode is open, or a camera's encoder failed.
        """
        episode = self._episode
        if episode is None:
            raise ROSRuntimeError("no episode is open: call begin_episode() first")
        frame_index = len(episode.rows["frame_index"])
        for index, cam in enumerate(self.cameras):
            frame = frames.get(cam.sensor_id)
            encoder = episode.encoders.get(cam.sensor_id) or self._start_encoder(episode, index, frame)
            if encoder is None:  # size still unknown: a black frame goes in once it is
                episode.unsized[cam.sensor_id] = episode.unsized.get(cam.sensor_id, 0) + 1
                row[schema.camera_column(cam.sensor_id, "repeated")] = True
                continue
            encoded = encoder.add(frame)
            if encoder.failed:
                episode.failed = True
            row[schema.camera_column(cam.sensor_id, "repeated")] = not encoded
            if frame is not None and encoded:
                self._sample(episode, cam.sensor_id, frame, frame_index)
        row["timestamp"] = frame_index / self.fps
        row["frame_index"] = frame_index
        row["episode_index"] = episode.idx
        row["index"] = self.total_frames + frame_index
        row["task_index"] = episode.task_index
        if frame_index / self.fps >= schema.TIMESTAMP_EXACT_S and not episode.long_warned:
            episode.long_warned = True
            _log.warning(
                "episode longer than float32 timestamps resolve within LeRobot's tolerance; end episodes sooner",
                episode=episode.idx,
                limit_s=schema.TIMESTAMP_EXACT_S,
            )
        absent = self._absent
        for name, values in episode.rows.items():
            value = row.get(name)
            values.append(absent[name] if value is None else value)

    def _start_encoder(self, episode: _Episode, index: int, frame: SensorFrame | None) -> StreamingVideoEncoder | None:
        """The episode's encoder for camera ``index``; ``None`` while its size is unknown and no frame came."""
        cam = self.cameras[index]
        if not cam.width:
            if frame is None:
                return None
            cam = self._size_camera(index, frame)
        encoder = episode.encoders[cam.sensor_id] = StreamingVideoEncoder(
            episode.folder / f"{cam.sensor_id}.mp4",
            self._encoder_process(cam, frame),
            fps=self.fps,
            width=cam.width,
            height=cam.height,
            vcodec=self.vcodec,
            overflow=self.overflow,
        )
        for _ in range(episode.unsized.pop(cam.sensor_id, 0)):
            encoder.add(None)
        return encoder

    def _encoder_process(self, cam: schema.CameraSpec, frame: SensorFrame | None) -> EncoderProcess:
        """The camera's encoder process, started once for the whole recording (slots sized from its frames)."""
        process = self._processes.get(cam.sensor_id)
        if process is None:
            slot_bytes = cam.width * cam.height * 4
            if frame is not None:
                slot_bytes = max(slot_bytes, frame.as_array().nbytes)
            process = self._processes[cam.sensor_id] = EncoderProcess(cam.sensor_id, slot_bytes=slot_bytes)
        return process

    def _size_camera(self, index: int, frame: SensorFrame) -> schema.CameraSpec:
        """Fix a camera's video size from its first frame (even, as 4:2:0 video needs)."""
        cam = schema.CameraSpec(frame.sensor_id, frame.width - frame.width % 2, frame.height - frame.height % 2)
        self.cameras[index] = cam
        self.features = self._features()
        return cam

    def end_episode(self, *, keep: bool = True, success: bool | None = None) -> EpisodeSummary:
        """Commit the open episode (``keep``) or discard it without a trace.

        An episode with no rows, or whose encoder fell behind under the ``fail`` policy, is discarded.

        Raises:
            ROSRuntimeError: No episode is open, or writing failed (the episode is then discarded).
        """
        import time  # noqa: PLC0415

        started = time.perf_counter()
        episode = self._episode
        if episode is None:
            raise ROSRuntimeError("no episode is open")
        self._episode = None
        frames = len(episode.rows["frame_index"])
        repeated = {cam: enc.repeated for cam, enc in episode.encoders.items()}
        if not keep or frames == 0 or episode.failed:
            if episode.failed:
                _log.error("episode discarded: a video encoder fell behind (policy 'fail')", episode=episode.idx)
            for encoder in episode.encoders.values():
                encoder.abort()
            shutil.rmtree(episode.folder, ignore_errors=True)
            return EpisodeSummary(episode.idx, frames, episode.task, False, repeated)
        try:
            self._commit(episode, frames, success)
        except Exception as exc:
            self._put_back(episode)
            if isinstance(exc, OSError):
                raise ROSRuntimeError(
                    f"cannot write episode {episode.idx} into {self.root}: {exc.strerror or exc}; "
                    f"the dataset keeps its {self.total_episodes} committed episode(s)"
                ) from exc
            raise
        return EpisodeSummary(episode.idx, frames, episode.task, True, repeated, time.perf_counter() - started)

    def _put_back(self, episode: _Episode) -> None:
        """After a failed commit: stop the encoders and undo what was moved (left for the next opening if it fails)."""
        for encoder in episode.encoders.values():
            with contextlib.suppress(Exception):  # an encoder that failed may be gone already
                encoder.abort()
        try:
            commit.discard(self.root, episode.folder, committed=self.total_episodes)
        except OSError as exc:
            _log.error(
                "could not put the dataset back after a failed commit; opening it again will",
                dataset=str(self.root),
                error=str(exc),
            )

    def close(self) -> None:
        """Discard an episode still open, stop the encoder processes and remove the staging area."""
        if self._episode is not None:
            self.end_episode(keep=False)
        for process in self._processes.values():
            process.close()
        self._processes.clear()
        try:
            commit.recover(self.root, self.total_episodes)
        except OSError as exc:
            _log.error("could not remove the staging area", dataset=str(self.root), error=str(exc))

    # -- commit ----------------------------------------------------------------------------

    def _commit(self, episode: _Episode, frames: int, success: bool | None) -> None:
        for cam in self.cameras:
            if cam.sensor_id not in episode.encoders:
                raise ROSRuntimeError(f"camera {cam.sensor_id} delivered no frame in episode {episode.idx}")
            written = episode.encoders[cam.sensor_id].finish()
            if written != frames:
                raise ROSRuntimeError(f"camera {cam.sensor_id}: {written} video frames for {frames} rows")
        folder = episode.folder
        table = pa.table(
            {name: pa.array(values, type=self._arrow.field(name).type) for name, values in episode.rows.items()}
        )
        layout.write_file(folder / "data.parquet", _parquet_bytes(table))
        episode_stats = self._episode_stats(episode, table)
        row = self._episode_row(episode, frames, episode_stats, success)
        layout.write_file(folder / "episode.parquet", _parquet_bytes(row))
        moves = [
            commit.Move(
                folder / f"{cam.sensor_id}.mp4",
                layout.video_file(self.root, schema.video_key(cam.sensor_id), episode.idx),
            )
            for cam in self.cameras
        ]
        moves.append(commit.Move(folder / "data.parquet", layout.data_file(self.root, episode.idx)))
        moves.append(commit.Move(folder / "episode.parquet", layout.episodes_file(self.root, episode.idx)))

        outcome = {
            "episode_index": episode.idx,
            "success": success,
            "repeated_frames": {cam: enc.repeated for cam, enc in episode.encoders.items()},
        }
        outcomes = [*self._outcomes, json.dumps(outcome)]
        tasks = dict(self._tasks)
        tasks.setdefault(episode.task, episode.task_index)
        merged = {
            name: stats.merge_stats([self._merged[name], values]) if name in self._merged else values
            for name, values in episode_stats.items()
        }
        info = self._info(self.total_episodes + 1, self.total_frames + frames, len(tasks))
        dataset_files = {  # info.json last: moving it into place is the commit
            layout.OUTCOMES_PATH: ("\n".join(outcomes) + "\n").encode("utf-8"),
            layout.TASKS_PATH: tasks_parquet_bytes(tasks),
            layout.STATS_PATH: json.dumps(stats.to_json(merged), indent=2).encode("utf-8"),
            layout.INFO_PATH: json.dumps(info, indent=2).encode("utf-8"),
        }
        for path, data in dataset_files.items():
            staged = folder / path
            layout.write_file(staged, data)
            moves.append(commit.Move(staged, self.root / path, replaces=True))
        commit.apply(self.root, folder, episode.idx, moves)
        # Committed: only now does the in-memory view move on.
        shutil.rmtree(folder, ignore_errors=True)
        self._outcomes = outcomes
        self._tasks = tasks
        self._merged = merged
        self.total_episodes += 1
        self.total_frames += frames

    def _info(self, episodes: int, frames: int, tasks: int) -> dict[str, Any]:
        return {
            "codebase_version": layout.CODEBASE_VERSION,
            "robot_type": self.robot_type,
            "total_episodes": episodes,
            "total_frames": frames,
            "total_tasks": tasks,
            "chunks_size": layout.CHUNKS_SIZE,
            "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 200,
            "fps": self.fps,
            "splits": {"train": f"0:{episodes}"},
            "data_path": layout.DATA_PATH,
            "video_path": layout.VIDEO_PATH if self.cameras else None,
            "features": self.features,
        }

    def _episode_stats(self, episode: _Episode, table: pa.Table) -> dict[str, dict[str, np.ndarray]]:
        out = {}
        for name in schema.stat_features(self.features):
            if name in table.column_names:
                values = np.asarray(table.column(name).to_pylist(), dtype=np.float64)
                out[name] = stats.vector_stats(values)
        for cam in self.cameras:
            # No sample means the video holds only black filler frames: their statistics are zeros.
            samples = episode.samples.get(cam.sensor_id) or [np.zeros((1, 1, 3), np.uint8)]
            out[schema.video_key(cam.sensor_id)] = stats.image_stats(samples, len(table))
        return out

    def _episode_row(
        self, episode: _Episode, frames: int, episode_stats: dict[str, dict[str, np.ndarray]], success: bool | None
    ) -> pa.Table:
        where = layout.chunk_file(episode.idx)
        row: dict[str, Any] = {
            "episode_index": [episode.idx],
            "tasks": [[episode.task]],
            "length": [frames],
            "data/chunk_index": [where["chunk_index"]],
            "data/file_index": [where["file_index"]],
            "dataset_from_index": [self.total_frames],
            "dataset_to_index": [self.total_frames + frames],
        }
        for cam in self.cameras:
            key = schema.video_key(cam.sensor_id)
            row[f"videos/{key}/chunk_index"] = [where["chunk_index"]]
            row[f"videos/{key}/file_index"] = [where["file_index"]]
            row[f"videos/{key}/from_timestamp"] = [0.0]
            row[f"videos/{key}/to_timestamp"] = [frames / self.fps]
        row["meta/episodes/chunk_index"] = [where["chunk_index"]]
        row["meta/episodes/file_index"] = [where["file_index"]]
        for feature, values in episode_stats.items():
            for name, value in values.items():
                row[f"stats/{feature}/{name}"] = [np.asarray(value).tolist()]
        return pa.table(row, schema=schema.episode_schema(self.features, stats.STAT_NAMES))

    @staticmethod
    def _sample(episode: _Episode, camera: str, frame: SensorFrame, frame_index: int) -> None:
        """Keep every n-th frame (subsampled) for camera statistics; n doubles whenever the sample fills up."""
        stride = episode.sample_stride.setdefault(camera, 1)
        if frame_index % stride:
            return
        samples = episode.samples.setdefault(camera, [])
        samples.append(_rgb_sample(frame))
        if len(samples) >= 2 * stats.IMAGE_SAMPLE_FRAMES:
            del samples[1::2]
            episode.sample_stride[camera] = stride * 2


def _rgb_sample(frame: SensorFrame) -> np.ndarray:
    """A subsampled ``[h, w, 3]`` RGB copy of a frame, as the video decodes it (grey repeated, BGR swapped)."""
    step = stats.IMAGE_SAMPLE_STRIDE
    array = frame.as_array()
    if array.ndim == 2:
        array = array[:, :, None]
    small = np.asarray(array[::step, ::step])
    if small.shape[2] == 1:
        return np.repeat(small, 3, axis=2)
    if frame.encoding in (FrameEncoding.BGR8, FrameEncoding.BGRA8):
        return np.ascontiguousarray(small[:, :, 2::-1])
    return np.ascontiguousarray(small[:, :, :3])


def _signature(feature: dict[str, Any]) -> tuple[Any, ...]:
    """What must match for two recordings to share a dataset: dtype, shape and, for videos, codec and pixels."""
    video = feature.get("info") or {}
    return (feature["dtype"], feature["shape"], video.get("video.codec"), video.get("video.pix_fmt"))


def tasks_parquet_bytes(tasks: dict[str, int]) -> bytes:
    """``meta/tasks.parquet``: a pandas frame indexed by the task string, with a ``task_index`` column."""
    ordered = sorted(tasks.items(), key=lambda item: item[1])
    table = pa.table(
        {"task_index": pa.array([i for _t, i in ordered], pa.int64()), "task": pa.array([t for t, _i in ordered])}
    )
    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [
            {"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object", "metadata": None}
        ],
        "columns": [
            {
                "name": "task_index",
                "field_name": "task_index",
                "pandas_type": "int64",
                "numpy_type": "int64",
                "metadata": None,
            },
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": None},
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    return _parquet_bytes(table.replace_schema_metadata({b"pandas": json.dumps(pandas_meta).encode("utf-8")}))


def _parquet_bytes(table: pa.Table) -> bytes:
    """``table`` as a parquet file in memory: written to disk by :func:`layout.write_file`, synced, like every file."""
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return bytes(sink.getvalue().to_pybytes())
