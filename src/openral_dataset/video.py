"""``StreamingVideoEncoder``: one camera's frames to a constant-frame-rate MP4 while recording, off the tick thread.

Frame ``i`` of an episode gets pts ``i`` in a ``1/fps`` time base, so a reader that seeks to
``i / fps`` finds exactly that frame (LeRobot's loader allows 1e-4 s). The encoder runs on its own
thread behind a bounded queue of frames. When the queue is full the frame is not held: a
*repeat* of the previous frame takes its place in the stream (the grid stays whole) and is
counted, or, under the ``fail`` policy, the episode is marked failed.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections import deque
from collections.abc import Callable
from enum import StrEnum
from fractions import Fraction
from functools import partial
from pathlib import Path
from typing import Any, Final

import numpy as np

from openral_core import FrameEncoding, ROSConfigError, ROSDependencyMissing, ROSRuntimeError, SensorFrame
from openral_dataset.layout import sync_file

try:
    import av
except ImportError as exc:
    raise ROSDependencyMissing("av", extra="dataset", needed_for="recording datasets") from exc

os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its banner to stderr unless told errors only

CODEC_OPTIONS: Final[dict[str, dict[str, str]]] = {
    # Preset 12, a keyframe every 2 frames, CRF 30: what LeRobot uses, and it keeps up on a small CPU.
    "libsvtav1": {"preset": "12", "g": "2", "crf": "30"},
    # No B-frames: every frame decodes on its own timeline, and Foxglove can show the stream.
    "h264": {"preset": "veryfast", "tune": "zerolatency", "g": "2", "crf": "23", "bf": "0"},
}
ENCODE_NICENESS: Final = 10
"""Niceness of the encoding threads (higher: lower priority than the tick and capture threads)."""
_PYAV_CODEC: Final = {"libsvtav1": "libsvtav1", "h264": "libx264"}
_INPUT_FORMAT: Final = {
    FrameEncoding.RGB8: "rgb24",
    FrameEncoding.BGR8: "bgr24",
    FrameEncoding.RGBA8: "rgba",
    FrameEncoding.BGRA8: "bgra",
    FrameEncoding.MONO8: "gray",
}
_REPEAT: Final = None


class OverflowPolicy(StrEnum):
    """What a recording does when a camera's encoder falls behind."""

    REPEAT = "repeat"
    """Repeat the previous frame in the video and flag the row: the episode survives."""
    FAIL = "fail"
    """Mark the episode failed: it is discarded instead of committed."""


def supported_codecs() -> list[str]:
    """Codec names accepted by ``--vcodec``."""
    return sorted(CODEC_OPTIONS)


class EncodeWorker:
    """A long-lived thread that encodes one camera, episode after episode.

    One thread for the whole recording, not one per episode: each new thread gets its own malloc
    arena, and an encoder's large buffers left in a new arena every episode make the process grow.
    Jobs run in the order they were submitted.
    """

    def __init__(self, name: str) -> None:
        self._jobs: deque[Callable[[], None]] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, job: Callable[[], None]) -> None:
        with self._cond:
            self._jobs.append(job)
            self._cond.notify()

    def close(self, timeout_s: float = 30.0) -> None:
        """Run what is queued, then stop. Idempotent."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        # Encoding yields the CPU to the tick thread: this thread, and the codec's own threads
        # (started from it, so they inherit its niceness), run at a lower priority.
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), ENCODE_NICENESS)
        while True:
            with self._cond:
                while not self._jobs and not self._closed:
                    self._cond.wait()
                if not self._jobs:
                    return
                job = self._jobs.popleft()
            job()


class StreamingVideoEncoder:
    """Encodes one camera of one episode into ``path`` as frames arrive.

    Args:
        path: The MP4 to write (a staging path: it is committed elsewhere).
        fps: The dataset's frame rate.
        width: Video width (frames of another size are scaled to it).
        height: Video height.
        vcodec: ``libsvtav1`` or ``h264``.
        max_pending: Frames held for the encoder before new ones are repeated instead.
        overflow: What to do when the encoder falls behind.
        worker: The camera's encoding thread; without one the encoder starts its own and stops it when done.

    Raises:
        ROSConfigError: An unknown codec, or a size the codec cannot encode.
    """

    def __init__(
        self,
        path: Path,
        *,
        fps: int,
        width: int,
        height: int,
        vcodec: str = "libsvtav1",
        max_pending: int = 64,
        overflow: OverflowPolicy = OverflowPolicy.REPEAT,
        worker: EncodeWorker | None = None,
    ) -> None:
        if vcodec not in CODEC_OPTIONS:
            raise ROSConfigError(
                f"unknown video codec '{vcodec}'", field="vcodec", hint=f"use one of {supported_codecs()}"
            )
        if width % 2 or height % 2:
            raise ROSConfigError(
                f"{width}x{height}: YUV 4:2:0 video needs an even width and height", field="sensors[].width"
            )
        self.path = path
        self.fps = fps
        self.width = width
        self.height = height
        self.vcodec = vcodec
        self.overflow = OverflowPolicy(overflow)
        self._max_pending = max_pending
        self._lock = threading.Lock()
        self._pixels_pending = 0
        self._stopped = False
        self._error: BaseException | None = None
        self.frames_written = 0
        self.repeated = 0
        self.failed = False
        """Under the ``fail`` policy: the encoder fell behind and the episode must be discarded."""
        path.parent.mkdir(parents=True, exist_ok=True)
        self._container: Any = av.open(str(path), "w")
        stream: Any = self._container.add_stream(_PYAV_CODEC[vcodec], rate=fps, options=CODEC_OPTIONS[vcodec])
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.codec_context.time_base = Fraction(1, fps)
        self._stream: Any = stream
        self._last: Any = None
        self._own_worker = worker is None
        self._worker = worker or EncodeWorker(f"openral-encode-{path.stem}")

    @property
    def pending(self) -> int:
        """Frames (with pixels) waiting for the encoder."""
        return self._pixels_pending

    def add(self, frame: SensorFrame | None) -> bool:
        """Append the next frame of the grid (``None``: repeat the previous one). Never blocks.

        Returns:
            ``True`` if the frame itself will be encoded, ``False`` if a repeat took its place.

        Raises:
            ROSRuntimeError: An earlier frame failed to encode.
        """
        with self._lock:
            if self._error is not None:
                raise ROSRuntimeError(f"video encoder for {self.path.name} failed: {self._error}") from self._error
            if frame is not None and self._pixels_pending >= self._max_pending:
                if self.overflow is OverflowPolicy.FAIL:
                    self.failed = True
                frame = _REPEAT
            if frame is _REPEAT:
                self.repeated += 1
            else:
                self._pixels_pending += 1
        self._worker.submit(partial(self._encode_one, frame))
        return frame is not None

    def finish(self) -> int:
        """Encode what is queued, flush the encoder, close and sync the file.

        Returns:
            Frames in the video.

        Raises:
            ROSRuntimeError: Encoding failed.
        """
        done = threading.Event()
        self._worker.submit(partial(self._flush, done))  # on the camera's thread, after every frame
        done.wait()
        self._release_worker()
        if self._error is not None:
            self._close_quietly()
            raise ROSRuntimeError(f"video encoder for {self.path.name} failed: {self._error}") from self._error
        sync_file(self.path)
        return self.frames_written

    def _flush(self, done: threading.Event) -> None:
        try:
            if self._error is None:
                for packet in self._stream.encode():
                    self._container.mux(packet)
                self._container.close()
        except Exception as exc:
            self._error = exc
        finally:
            done.set()

    def abort(self) -> None:
        """Stop without finishing the file (the episode is discarded)."""
        self._stopped = True
        done = threading.Event()
        self._worker.submit(done.set)
        done.wait()
        self._release_worker()
        self._close_quietly()

    def _release_worker(self) -> None:
        if self._own_worker:
            self._worker.close()

    def _close_quietly(self) -> None:
        with contextlib.suppress(Exception):
            self._container.close()

    def _encode_one(self, frame: SensorFrame | None) -> None:
        try:
            if not self._stopped and self._error is None:
                self._encode(frame)
        except Exception as exc:  # reported by add() and finish()
            self._error = exc
        finally:
            if frame is not None:
                with self._lock:
                    self._pixels_pending -= 1

    def _encode(self, frame: SensorFrame | None) -> None:
        if frame is None:
            video_frame = self._last if self._last is not None else self._black()
        else:
            video_frame = self._convert(frame)
        self._last = video_frame
        # The encoder takes its own reference to the picture when the frame is sent, with the pts
        # of that moment: a repeat re-sends the same picture with the next pts.
        video_frame.pts = self.frames_written
        for packet in self._stream.encode(video_frame):
            self._container.mux(packet)
        self.frames_written += 1

    def _convert(self, frame: SensorFrame) -> Any:
        """The frame as a picture of the video's size and pixel format (one copy in, one scale)."""
        fmt = _INPUT_FORMAT.get(frame.encoding)
        if fmt is None:
            raise ROSRuntimeError(f"frames encoded as {frame.encoding} cannot be recorded as video")
        source = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame.as_array()), format=fmt)
        return source.reformat(width=self.width, height=self.height, format="yuv420p")

    def _black(self) -> Any:
        black = av.VideoFrame.from_ndarray(np.zeros((self.height, self.width, 3), np.uint8), format="rgb24")
        return black.reformat(format="yuv420p")
