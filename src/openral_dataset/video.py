"""``StreamingVideoEncoder``: one camera's frames to a constant-frame-rate MP4 while recording, out of the process.

Frame ``i`` of an episode gets pts ``i`` in a ``1/fps`` time base, so a reader that seeks to
``i / fps`` finds exactly that frame (LeRobot's loader allows 1e-4 s). Each camera is encoded by
its own child process for the whole recording (:mod:`openral_dataset.encoder_process`); a frame
costs this process one copy into a shared-memory slot. When every slot is still waiting for the
encoder, the frame is not held: a *repeat* of the previous frame takes its place in the stream
(the grid stays whole) and is counted, or, under the ``fail`` policy, the episode is marked failed.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import subprocess
import sys
import threading
import time
from enum import StrEnum
from multiprocessing import shared_memory
from pathlib import Path
from typing import Final

import numpy as np

from openral_core import FrameEncoding, ROSConfigError, ROSDependencyMissing, ROSRuntimeError, SensorFrame
from openral_dataset.encoder_process import CODEC_OPTIONS, HEADER_BYTES, read_message, write_message

if importlib.util.find_spec("av") is None:  # the encoder processes import it
    raise ROSDependencyMissing("av", extra="dataset", needed_for="recording datasets")

_INPUT_FORMAT: Final = {
    FrameEncoding.RGB8: "rgb24",
    FrameEncoding.BGR8: "bgr24",
    FrameEncoding.RGBA8: "rgba",
    FrameEncoding.BGRA8: "bgra",
    FrameEncoding.MONO8: "gray",
}
_CHILD: Final = "openral_dataset.encoder_process"
_COPY_BAND_BYTES: Final = 128 * 1024
_WAIT_POLL_S: Final = 0.0005
_WAIT_LIMIT_S: Final = 30.0
DEFAULT_SLOTS: Final = 32
"""Frames a camera's encoder may fall behind by before frames are repeated (about 1 s at 30 fps)."""


class OverflowPolicy(StrEnum):
    """What a recording does when a camera's encoder falls behind."""

    REPEAT = "repeat"
    """Repeat the previous frame in the video and flag the row: the episode survives."""
    FAIL = "fail"
    """Mark the episode failed: it is discarded instead of committed."""
    WAIT = "wait"
    """Wait for the encoder: for simulations, where no tick has a deadline and every frame must be kept."""


def supported_codecs() -> list[str]:
    """Codec names accepted by ``--vcodec``."""
    return sorted(CODEC_OPTIONS)


class EncoderProcess:
    """One camera's encoder process and its ring of frame slots, for the whole recording.

    The ring is sized from the first frame; a frame that does not fit is refused with an error.
    Thread-safety: one thread (the recorder's worker) drives it.

    Args:
        name: For error messages (the camera's id).
        slot_bytes: Size of one slot (the camera's frame size in bytes).
        slots: How many frames may wait for the encoder.
    """

    def __init__(self, name: str, *, slot_bytes: int, slots: int = DEFAULT_SLOTS) -> None:
        self.name = name
        self.slot_bytes = slot_bytes
        self.slots = slots
        self._ring = shared_memory.SharedMemory(create=True, size=HEADER_BYTES + slots * slot_bytes)
        self._consumed = np.ndarray((1,), np.int64, buffer=self._ring.buf, offset=0)
        self._consumed[0] = 0
        self._written = 0
        # The parent-death signal fires when the creating thread exits; the recorder's worker
        # lives as long as the recording.
        self._process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "openral_dataset.encoder_process",
                str(os.getpid()),
                self._ring.name,
                str(slot_bytes),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        self._lock = threading.Lock()

    @property
    def waiting(self) -> int:
        """Frames copied in that the encoder has not taken yet."""
        return self._written - int(self._consumed[0])

    def send(self, message: tuple[object, ...]) -> None:
        """Send one message to the encoder.

        Raises:
            ROSRuntimeError: The encoder process is gone.
        """
        stdin = self._process.stdin
        assert stdin is not None
        try:
            write_message(stdin, message)
        except (BrokenPipeError, OSError) as exc:
            raise ROSRuntimeError(f"the video encoder of camera {self.name} exited ({self._process.poll()})") from exc

    def put_frame(self, pixels: np.ndarray, fmt: str) -> bool:
        """Copy ``pixels`` into the next free slot and queue it; ``False`` if every slot is taken.

        Raises:
            ROSRuntimeError: The frame is larger than a slot, or the encoder process is gone.
        """
        if pixels.nbytes > self.slot_bytes:
            raise ROSRuntimeError(
                f"camera {self.name}: a {pixels.nbytes}-byte frame does not fit the {self.slot_bytes}-byte "
                "slots sized from its first frame (did the camera change resolution?)"
            )
        if self.waiting >= self.slots:
            return False
        slot = self._written % self.slots
        offset = HEADER_BYTES + slot * self.slot_bytes
        target = np.ndarray(pixels.shape, np.uint8, buffer=self._ring.buf, offset=offset)
        # In bands of rows: between bands the tick thread can take the interpreter lock (a whole
        # VGA frame is one 60 µs copy that nothing could interrupt).
        rows = max(1, _COPY_BAND_BYTES // max(1, pixels[0].nbytes))
        for start in range(0, pixels.shape[0], rows):
            target[start : start + rows] = pixels[start : start + rows]
        self._written += 1
        height, width = pixels.shape[:2]
        channels = pixels.shape[2] if pixels.ndim == 3 else 1
        self.send(("frame", slot, height, width, channels, fmt))
        return True

    def request(self, message: tuple[object, ...]) -> tuple[object, ...]:
        """Send a message the encoder answers, and wait for the answer.

        Raises:
            ROSRuntimeError: The encoder process is gone.
        """
        self.send(message)
        stdout = self._process.stdout
        assert stdout is not None
        answer = read_message(stdout)
        if answer is None:
            raise ROSRuntimeError(f"the video encoder of camera {self.name} exited ({self._process.poll()})")
        return answer

    def close(self, timeout_s: float = 10.0) -> None:
        """Stop the process and free the ring. Idempotent."""
        if self._process.stdin is not None and not self._process.stdin.closed:
            with contextlib.suppress(OSError):
                self._process.stdin.close()
        try:
            self._process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        if self._process.stdout is not None:
            self._process.stdout.close()
        del self._consumed
        self._ring.close()
        with contextlib.suppress(FileNotFoundError):
            self._ring.unlink()


class StreamingVideoEncoder:
    """Encodes one camera of one episode into ``path`` as frames arrive, through the camera's encoder process.

    Args:
        path: The MP4 to write (a staging path: it is committed elsewhere).
        process: The camera's encoder process.
        fps: The dataset's frame rate.
        width: Video width (frames of another size are scaled to it).
        height: Video height.
        vcodec: ``libsvtav1`` or ``h264``.
        overflow: What to do when the encoder falls behind.

    Raises:
        ROSConfigError: An unknown codec, or a size the codec cannot encode.
    """

    def __init__(
        self,
        path: Path,
        process: EncoderProcess,
        *,
        fps: int,
        width: int,
        height: int,
        vcodec: str = "libsvtav1",
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
        self.width = width
        self.height = height
        self.overflow = OverflowPolicy(overflow)
        self.frames_sent = 0
        self.repeated = 0
        self.failed = False
        """Under the ``fail`` policy: the encoder fell behind and the episode must be discarded."""
        self._process = process
        path.parent.mkdir(parents=True, exist_ok=True)
        process.send(("open", str(path), fps, width, height, vcodec))

    def add(self, frame: SensorFrame | None) -> bool:
        """Append the next frame of the grid (``None``: repeat the previous one). Never blocks on the encoder.

        Returns:
            ``True`` if the frame itself will be encoded, ``False`` if a repeat took its place.

        Raises:
            ROSRuntimeError: A frame the encoder cannot take, or the encoder process is gone.
        """
        taken = False
        if frame is not None:
            fmt = _INPUT_FORMAT.get(frame.encoding)
            if fmt is None:
                raise ROSRuntimeError(f"frames encoded as {frame.encoding} cannot be recorded as video")
            pixels = frame.as_array()
            taken = self._process.put_frame(pixels, fmt)
            if not taken and self.overflow is OverflowPolicy.WAIT:
                taken = self._wait_for_slot(pixels, fmt)
            if not taken and self.overflow is OverflowPolicy.FAIL:
                self.failed = True
        if not taken:
            self.repeated += 1
            self._process.send(("repeat",))
        self.frames_sent += 1
        return taken

    def _wait_for_slot(self, pixels: np.ndarray, fmt: str) -> bool:
        """Retry until the encoder frees a slot (it always does, unless it died: then this raises)."""
        deadline = time.monotonic() + _WAIT_LIMIT_S
        while time.monotonic() < deadline:
            time.sleep(_WAIT_POLL_S)
            if self._process.put_frame(pixels, fmt):
                return True
        raise ROSRuntimeError(f"the video encoder of camera {self._process.name} took no frame for {_WAIT_LIMIT_S} s")

    def finish(self) -> int:
        """Encode what is queued, flush the encoder, close and sync the file.

        Returns:
            Frames in the video.

        Raises:
            ROSRuntimeError: Encoding failed.
        """
        answer = self._process.request(("finish",))
        if answer[0] != "finished":
            raise ROSRuntimeError(f"video of camera {self._process.name} ({self.path.name}): {answer[1]}")
        frames = answer[1]
        assert isinstance(frames, int)
        return frames

    def abort(self) -> None:
        """Stop without finishing the file (the episode is discarded)."""
        self._process.request(("abort",))
