"""``LeRobotDatasetSink``: episodes written as LeRobotDataset v3.0 with pyarrow and PyAV, each committed atomically.

An episode is built in a staging folder outside ``data/``, ``meta/`` and ``videos/``: its rows in
memory, one streaming video encoder per camera (frames are encoded while recording). Committing
writes and syncs its data and episode parquet files and the dataset's new ``tasks.parquet``,
``stats.json``, outcome lines and ``info.json`` there, then moves them into place, ``info.json``
last (:mod:`openral_dataset.commit`): until that rename the episode does not exist. A failed
commit is put back at once; one a crash interrupted, the next time the dataset is opened.

Opening refuses what it cannot trust before it touches a file (:mod:`openral_dataset.opening`);
it happens when the sink is built, or at :meth:`LeRobotDatasetSink.open` for a sink built with
``defer_open`` (a recorder built from a deployment's ``observers:`` opens nothing until it starts).
The metadata a commit writes is :mod:`openral_dataset.meta_writer`.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from openral_core import ROSConfigError, ROSDependencyMissing, ROSRuntimeError, SensorFrame
from openral_dataset import commit, layout, meta_writer, opening, schema, stats
from openral_dataset.episode import EpisodeSummary, StagedEpisode
from openral_dataset.meta_reader import read_tasks
from openral_dataset.video import EncoderProcess, OverflowPolicy, StreamingVideoEncoder

try:
    import pyarrow as pa
except ImportError as exc:
    raise ROSDependencyMissing("pyarrow", extra="dataset", needed_for="recording datasets") from exc

__all__ = ["EpisodeSummary", "LeRobotDatasetSink", "read_tasks"]

_log = structlog.get_logger(__name__)


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
        field: The option or parameter that named ``root``, for errors.
        defer_open: Open the folder at :meth:`open` rather than here (building then touches no file).
        takeover: Record the takeover columns (:data:`~openral_dataset.schema.TAKEOVER_COLUMNS`).

    Raises:
        ROSConfigError: A bad rate, codec or camera name; and, unless ``defer_open``, what
            :meth:`open` raises.
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
        field: str = "--dataset-out",
        defer_open: bool = False,
        takeover: bool = False,
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
        self.takeover = takeover
        self.overflow = OverflowPolicy(overflow)
        self.features = self._features()
        self._arrow = schema.arrow_schema(self.features)
        self._absent = schema.absent_values(self.features)
        self._episode: StagedEpisode | None = None
        self._processes: dict[str, EncoderProcess] = {}
        self._tasks: dict[str, int] = {}
        self._merged: dict[str, dict[str, np.ndarray]] = {}
        self._outcomes: list[str] = []
        self.total_episodes = 0
        self.total_frames = 0
        self._resume = resume
        self._field = field
        self._opened = False
        if not defer_open:
            self.open()

    def _features(self) -> dict[str, dict[str, Any]]:
        return schema.features(
            self.joint_names,
            self.cameras,
            fps=self.fps,
            vcodec=self.vcodec,
            action_names=self.action_names,
            environment_state_names=self.environment_state_names,
            takeover=self.takeover,
        )

    # -- opening ---------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """:meth:`open` has succeeded: episodes can be recorded."""
        return self._opened

    def open(self) -> None:
        """Open the folder for recording (:mod:`openral_dataset.opening`); idempotent.

        A new dataset's folder is created; a resumed one's cameras whose size was left open take
        the dataset's, and its totals, tasks, outcomes and statistics are read to go on from.

        Raises:
            ROSConfigError: ``root`` is a file; it holds a dataset without ``resume``, or one whose
                metadata is damaged or whose rate or features differ from this recording's; it holds
                other files; it cannot be written.
        """
        if self._opened:
            return
        found = opening.existing(self.root, resume=self._resume, field=self._field)
        if found is None:
            opening.prepare_new(self.root, field=self._field)
        else:
            self._adopt_sizes(found.features)
            opening.check_compatible(self.root, found, fps=self.fps, features=self.features, field=self._field)
            resumed = opening.resume(self.root, found, field=self._field)
            self.total_episodes = resumed.episodes
            self.total_frames = resumed.frames
            self._tasks = resumed.tasks
            self._outcomes = resumed.outcomes
            self._merged = resumed.stats
        self._opened = True

    def _adopt_sizes(self, features: dict[str, dict[str, Any]]) -> None:
        """Cameras whose size was left open take the size the dataset already has."""
        for index, cam in enumerate(self.cameras):
            spec = features.get(schema.video_key(cam.sensor_id))
            if not cam.width and spec is not None and spec["dtype"] == "video":
                height, width, _channels = spec["shape"]
                self.cameras[index] = schema.CameraSpec(cam.sensor_id, width, height)
        self.features = self._features()

    # -- episodes --------------------------------------------------------------------------

    @property
    def episode_open(self) -> bool:
        return self._episode is not None

    def begin_episode(self, task: str) -> int:
        """Start the next episode; returns its index.

        Raises:
            ROSRuntimeError: An episode is already open, or the dataset was never opened.
        """
        if not self._opened:
            raise ROSRuntimeError(f"the dataset {self.root} was not opened: call open() (a recorder's start()) first")
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
        self._episode = StagedEpisode(idx, task, task_index, folder, {name: [] for name in self._arrow.names})
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
        frame_index = episode.frames
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
                episode.sample(cam.sensor_id, frame, frame_index)
        row["timestamp"] = frame_index / self.fps
        row["frame_index"] = frame_index
        row["episode_index"] = episode.idx
        row["index"] = self.total_frames + frame_index
        row["task_index"] = episode.task_index
        episode.append(row, self._absent, fps=self.fps)

    def _start_encoder(
        self, episode: StagedEpisode, index: int, frame: SensorFrame | None
    ) -> StreamingVideoEncoder | None:
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
        started = time.perf_counter()
        episode = self._episode
        if episode is None:
            raise ROSRuntimeError("no episode is open")
        self._episode = None
        frames = episode.frames
        if not keep or frames == 0 or episode.failed:
            if episode.failed:
                _log.error("episode discarded: a video encoder fell behind (policy 'fail')", episode=episode.idx)
            episode.discard()
            return EpisodeSummary(episode.idx, frames, episode.task, False, episode.repeated_frames)
        try:
            self._commit(episode, success)
        except Exception as exc:
            self._put_back(episode)
            if isinstance(exc, OSError):
                raise ROSRuntimeError(
                    f"cannot write episode {episode.idx} into {self.root}: {exc.strerror or exc}; "
                    f"the dataset keeps its {self.total_episodes} committed episode(s)"
                ) from exc
            raise
        close_s = time.perf_counter() - started
        return EpisodeSummary(episode.idx, frames, episode.task, True, episode.repeated_frames, close_s)

    def _put_back(self, episode: StagedEpisode) -> None:
        """After a failed commit: stop the encoders and undo what was moved (left for the next opening if it fails)."""
        episode.abort_videos()
        try:
            commit.discard(self.root, episode.folder, committed=self.total_episodes)
        except OSError as exc:
            _log.error(
                "could not put the dataset back after a failed commit; opening it again will",
                dataset=str(self.root),
                error=str(exc),
            )

    def close(self) -> None:
        """Discard an episode still open, stop the encoder processes and remove the staging area.

        A sink never opened touches no file.
        """
        if self._episode is not None:
            self.end_episode(keep=False)
        for process in self._processes.values():
            process.close()
        self._processes.clear()
        if not self._opened:
            return
        try:
            commit.recover(self.root, self.total_episodes)
        except OSError as exc:
            _log.error("could not remove the staging area", dataset=str(self.root), error=str(exc))

    # -- commit ----------------------------------------------------------------------------

    def _commit(self, episode: StagedEpisode, success: bool | None) -> None:
        """Stage the episode's files and the dataset's new metadata, then move them into place, ``info.json`` last."""
        episode.finish_videos(self.cameras)
        folder, frames = episode.folder, episode.frames
        table = pa.table(
            {name: pa.array(values, type=self._arrow.field(name).type) for name, values in episode.rows.items()}
        )
        episode_stats = episode.statistics(self.features, table, self.cameras)
        row = meta_writer.episode_row(
            episode_idx=episode.idx,
            task=episode.task,
            frames=frames,
            first_index=self.total_frames,
            fps=self.fps,
            features=self.features,
            episode_stats=episode_stats,
        )
        layout.write_file(folder / "data.parquet", meta_writer.parquet_bytes(table))
        layout.write_file(folder / "episode.parquet", meta_writer.parquet_bytes(row))
        moves = [
            commit.Move(
                folder / f"{cam.sensor_id}.mp4",
                layout.video_file(self.root, schema.video_key(cam.sensor_id), episode.idx),
            )
            for cam in self.cameras
        ]
        moves.append(commit.Move(folder / "data.parquet", layout.data_file(self.root, episode.idx)))
        moves.append(commit.Move(folder / "episode.parquet", layout.episodes_file(self.root, episode.idx)))

        outcome = meta_writer.outcome_line(episode.idx, success=success, repeated_frames=episode.repeated_frames)
        outcomes = [*self._outcomes, outcome]
        tasks = dict(self._tasks)
        tasks.setdefault(episode.task, episode.task_index)
        merged = {
            name: stats.merge_stats([self._merged[name], values]) if name in self._merged else values
            for name, values in episode_stats.items()
        }
        info = meta_writer.info(
            robot_type=self.robot_type,
            fps=self.fps,
            features=self.features,
            episodes=self.total_episodes + 1,
            frames=self.total_frames + frames,
            tasks=len(tasks),
        )
        dataset_files = {  # info.json last: moving it into place is the commit
            layout.OUTCOMES_PATH: meta_writer.outcomes_bytes(outcomes),
            layout.TASKS_PATH: meta_writer.tasks_parquet_bytes(tasks),
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
