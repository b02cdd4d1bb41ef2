"""``EpisodeVideoWriter``: MP4 videos of the first episodes of a run, encoded off the tick thread.

Each step tick's frame of one camera (the frame the skill saw) goes to the episode's video, one
file per episode (``<prefix>_episode<N>.mp4``), H.264 at the loop's rate. It is the ``episode_video``
observer: ``sim run --save-video`` stands for one entry, and a benchmark's ``--videos`` gives one to
every unit of episodes (each films only the episodes below its ``episodes``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import structlog
from pydantic import BaseModel, ConfigDict, Field

from openral_core import ObserverContext, ROSConfigError, ROSDependencyMissing, TickResult, WorldState
from openral_core.config import validate_model
from openral_core.config_files import resolve_user_path
from openral_observability.queued_observer import QueuedObserver

try:
    import av
except ImportError as exc:
    raise ROSDependencyMissing("av", extra="dataset", needed_for="saving evaluation videos") from exc

_log = structlog.get_logger(__name__)

_PARAMS_FIELD = "observers[].params"


class EpisodeVideoParams(BaseModel):
    """Parameters of the ``episode_video`` observer."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    folder: str = Field(
        min_length=1, description="Where the videos go (relative to the loop's folder); created at start."
    )
    episodes: int = Field(default=3, ge=1, description="How many episodes are filmed: those numbered below this.")
    prefix: str | None = Field(
        default=None,
        min_length=1,
        pattern=r"^[^/\\\x00]+$",
        description="File name prefix, no folder (default: the robot, or the scene's environment).",
    )
    camera: str | None = Field(default=None, min_length=1, description="The camera filmed (default: the first).")


class EpisodeVideoWriter(QueuedObserver):
    """Writes ``camera``'s frames of episodes ``0 .. max_episodes - 1`` into ``folder``.

    Args:
        folder: Where the videos go (created at :meth:`start`).
        camera: The scene camera to film.
        fps: Frames per second of the video (the loop's rate).
        max_episodes: How many episodes are filmed (the first ones).
        prefix: File name prefix (a scene's name).
    """

    def __init__(self, folder: Path, *, camera: str, fps: float, max_episodes: int, prefix: str) -> None:
        self.folder = folder
        self.camera = camera
        self.fps = max(1, round(fps))
        self.max_episodes = max_episodes
        self.prefix = prefix
        self.written: list[Path] = []
        self._container: Any = None
        self._stream: Any = None
        self._path: Path | None = None
        super().__init__(name="openral-sim-video", max_queue=1 << 16)

    @classmethod
    def from_config(cls, params: Mapping[str, Any], context: ObserverContext) -> EpisodeVideoWriter:
        """Plugin constructor (observer ``episode_video``); ``params`` are :class:`EpisodeVideoParams`.

        Opens nothing: the folder is created by :meth:`start`. Errors name ``context.option``
        (``--save-video``) when the entry stands for one.

        Raises:
            ROSConfigError: A wrong parameter; the loop has no camera, or not the one named.
        """
        field = context.option or _PARAMS_FIELD
        config = validate_model(EpisodeVideoParams, dict(params), field_prefix=field)
        cameras = context.camera_ids()
        if not cameras:
            raise ROSConfigError(
                "the scene renders no camera to film", field="cameras", hint="add one under cameras: in the scene"
            )
        camera = config.camera or cameras[0]
        if camera not in cameras:
            raise ROSConfigError(
                f"no camera {camera!r} to film; the cameras are {cameras}",
                field=context.option or f"{_PARAMS_FIELD}.camera",
            )
        return cls(
            resolve_user_path(config.folder, context.base_dir, field=context.option or f"{_PARAMS_FIELD}.folder"),
            camera=camera,
            fps=context.rate_hz,
            max_episodes=config.episodes,
            prefix=config.prefix or context.robot_id,
        )

    def start(self) -> None:
        """Create the folder (the runner calls this at activation, before the first tick). Idempotent."""
        self.folder.mkdir(parents=True, exist_ok=True)

    def handle_episode_start(self, episode_idx: int, task: str) -> None:
        self._close_video()
        if episode_idx < self.max_episodes:
            self._path = self.folder / f"{self.prefix}_episode{episode_idx}.mp4"

    def handle_tick(self, tick: TickResult, world: WorldState | None) -> None:
        if self._path is None or tick.step_idx is None or world is None or not world.image_frames:
            return
        frame = world.image_frames.get(self.camera)
        if frame is None:
            return
        pixels = frame.as_array()
        if self._container is None:
            self._container = av.open(str(self._path), mode="w")
            self._stream = self._container.add_stream("h264", rate=self.fps)
            self._stream.width = frame.width - frame.width % 2
            self._stream.height = frame.height - frame.height % 2
            self._stream.pix_fmt = "yuv420p"
        image = av.VideoFrame.from_ndarray(pixels[: self._stream.height, : self._stream.width], format="rgb24")
        for packet in self._stream.encode(image):
            self._container.mux(packet)

    def handle_episode_end(self, episode_idx: int, *, success: bool, keep: bool) -> None:
        self._close_video()

    def handle_close(self) -> None:
        self._close_video()

    def _close_video(self) -> None:
        if self._container is not None:
            for packet in self._stream.encode():
                self._container.mux(packet)
            self._container.close()
            assert self._path is not None
            self.written.append(self._path)
            _log.info("episode video written", path=str(self._path))
        self._container = None
        self._stream = None
        self._path = None
