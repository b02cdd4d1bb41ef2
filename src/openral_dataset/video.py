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
from enum import StrEnum
from fractions import Fraction
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
        self._pending: deque[SensorFrame | None] = deque()
        self._pixels_pending = 0
        self._cond = threading.Condition()
        self._finishing = False
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
        self._thread = threading.Thread(target=self._run, name=f"openral-encode-{path.stem}", daemon=True)
        self._thread.start()

    @property
    def pending(self) -> int:
        """Frames (with pixels) waiting for the encoder."""
        return self._pixels_pending

    def add(self, frame: SensorFrame | None) -> bool:
        """Append the next frame of the grid (``None``: repeat the previous one). Never blocks.

        Returns:
            ``True`` if the frame itself will be encoded, ``False`` if a repeat took its place.
        """
        with self._cond:
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
            self._pending.append(frame)
            self._cond.notify()
            return frame is not None

    def finish(self) -> int:
        """Encode what is queued, flush the encoder, close and sync the file.

        Returns:
            Frames in the video.

        Raises:
            ROSRuntimeError: Encoding failed.
        """
        with self._cond:
            self._finishing = True
            self._cond.notify()
        self._thread.join()
        if self._error is not None:
            self._close_quietly()
            raise ROSRuntimeError(f"video encoder for {self.path.name} failed: {self._error}") from self._error
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        sync_file(self.path)
        return self.frames_written

    def abort(self) -> None:
        """Stop without finishing the file (the episode is discarded)."""
        with self._cond:
            self._finishing = True
            self._pending.clear()
            self._cond.notify()
        self._thread.join()
        self._close_quietly()

    def _close_quietly(self) -> None:
        with contextlib.suppress(Exception):
            self._container.close()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._finishing:
                    self._cond.wait()
                if not self._pending:
                    return
                frame = self._pending.popleft()
            try:
                self._encode(frame)
            except Exception as exc:  # reported by add() and finish()
                with self._cond:
                    self._error = exc
                    self._pending.clear()
                return
            finally:
                if frame is not None:
                    with self._cond:
                        self._pixels_pending -= 1

    def _encode(self, frame: SensorFrame | None) -> None:
        if frame is None:
            video_frame = self._last if self._last is not None else self._black()
        else:
            video_frame = self._convert(frame)
            self._last = video_frame
        out = av.VideoFrame.from_ndarray(video_frame, format="rgb24")
        out.pts = self.frames_written
        for packet in self._stream.encode(out):
            self._container.mux(packet)
        self.frames_written += 1

    def _convert(self, frame: SensorFrame) -> np.ndarray:
        fmt = _INPUT_FORMAT.get(frame.encoding)
        if fmt is None:
            raise ROSRuntimeError(f"frames encoded as {frame.encoding} cannot be recorded as video")
        source = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame.as_array()), format=fmt)
        rgb: np.ndarray = source.reformat(width=self.width, height=self.height, format="rgb24").to_ndarray()
        return rgb

    def _black(self) -> np.ndarray:
        return np.zeros((self.height, self.width, 3), np.uint8)
