"""``EpisodeVideoWriter``: MP4 videos of the first episodes of an evaluation, encoded off the tick thread.

Each step tick's frame of one camera (the frame the skill saw) goes to the episode's video, one
file per episode (``<scene>_episode<N>.mp4``), H.264 at the env's control rate.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import structlog

from openral_core import ROSDependencyMissing, TickResult, WorldState
from openral_observability.queued_observer import QueuedObserver

try:
    import av
except ImportError as exc:
    raise ROSDependencyMissing("av", extra="dataset", needed_for="saving evaluation videos") from exc

_log = structlog.get_logger(__name__)


class EpisodeVideoWriter(QueuedObserver):
    """Writes ``camera``'s frames of episodes ``0 .. max_episodes - 1`` into ``folder``.

    Args:
        folder: Where the videos go (created).
        camera: The scene camera to film.
        fps: Frames per second of the video (the env's control rate).
        max_episodes: How many episodes are filmed (the first ones).
        prefix: File name prefix (the scene's name).
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
        folder.mkdir(parents=True, exist_ok=True)
        super().__init__(name="openral-sim-video", max_queue=1 << 16)

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
