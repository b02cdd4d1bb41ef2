"""A camera's video encoder in its own process: encoding never holds the runner's interpreter lock.

PyAV holds Python's interpreter lock while a frame is converted and encoded (measured: a thread
encoding 640x480 AV1 at 60 fps delays another thread's wake-ups by tens of ms at p99). So each
recorded camera gets a child process (``python -m openral_dataset.encoder_process``) for the whole
recording. Pixels travel through a ring of shared-memory slots, the parent copying a frame in and
the child copying it out; the messages on the child's stdin only name the slot. The child counts
the slots it has copied out in the ring's header, so the parent knows which slots are free without
waiting for an answer. Only ``finish`` and ``abort`` are answered (on the child's stdout).

Messages (4-byte little-endian length, then a pickled tuple):
``("open", path, fps, width, height, vcodec)``, ``("frame", slot, height, width, channels, fmt)``,
``("repeat",)``, ``("finish",)`` (answered ``("finished", frames)`` or ``("error", message)``),
``("abort",)`` (answered ``("aborted",)``). End of input: the child exits. It runs at a lower
priority than the runner, ignores SIGINT/SIGTERM (the parent finishes the episode), and dies
with its parent.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import pickle
import signal
import struct
import sys
from fractions import Fraction
from typing import IO, Any, Final

NICENESS: Final = 10
"""How much lower than the runner an encoder runs: where cores are short, the tick wins."""
HEADER_BYTES: Final = 64
"""The ring's header: the count of slots the child has copied out (int64), then padding."""
CODEC_OPTIONS: Final[dict[str, dict[str, str]]] = {
    # Preset 12, a keyframe every 2 frames, CRF 30: what LeRobot uses, and it keeps up on a small CPU.
    "libsvtav1": {"preset": "12", "g": "2", "crf": "30"},
    # No B-frames: every frame decodes on its own timeline, and Foxglove can show the stream.
    "h264": {"preset": "veryfast", "tune": "zerolatency", "g": "2", "crf": "23", "bf": "0"},
}
PYAV_CODEC: Final = {"libsvtav1": "libsvtav1", "h264": "libx264"}
_LENGTH = struct.Struct("<I")
_PR_SET_PDEATHSIG: Final = 1


def write_message(stream: IO[bytes], message: tuple[Any, ...]) -> None:
    """Send one length-prefixed pickled message."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(_LENGTH.pack(len(data)) + data)
    stream.flush()


def read_message(stream: IO[bytes]) -> tuple[Any, ...] | None:
    """Receive one message; ``None`` at end of input."""
    head = stream.read(_LENGTH.size)
    if len(head) < _LENGTH.size:
        return None
    (length,) = _LENGTH.unpack(head)
    data = stream.read(length)
    if len(data) < length:
        return None
    message: tuple[Any, ...] = pickle.loads(data)
    return message


class _Encoder:
    """The child's side: one episode's MP4 at a time."""

    def __init__(self, ring: Any, slot_bytes: int) -> None:
        import numpy as np  # noqa: PLC0415  (the child only)

        self._np = np
        self._ring = ring
        self._slot_bytes = slot_bytes
        self._consumed = np.ndarray((1,), np.int64, buffer=ring.buf, offset=0)
        self._container: Any = None
        self._stream: Any = None
        self._last: Any = None
        self._frames = 0
        self._path = ""
        self._error: str | None = None

    def open(self, path: str, fps: int, width: int, height: int, vcodec: str) -> None:
        import av  # noqa: PLC0415

        self._close_quietly()
        self._path, self._frames, self._last, self._error = path, 0, None, None
        try:
            self._container = av.open(path, "w")
            stream = self._container.add_stream(PYAV_CODEC[vcodec], rate=fps, options=CODEC_OPTIONS[vcodec])
            stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
            stream.codec_context.time_base = Fraction(1, fps)
            self._stream = stream
        except Exception as exc:
            self._error = f"cannot open {path}: {exc}"

    def frame(self, slot: int, height: int, width: int, channels: int, fmt: str) -> None:
        import av  # noqa: PLC0415

        np = self._np
        try:
            offset = HEADER_BYTES + slot * self._slot_bytes
            shape = (height, width, channels) if channels > 1 else (height, width)
            pixels = np.ndarray(shape, np.uint8, buffer=self._ring.buf, offset=offset)
            source = av.VideoFrame.from_ndarray(pixels, format=fmt)  # copies out of the slot
        finally:
            self._consumed[0] += 1  # the slot is free again
        if self._stream is None or self._error is not None:
            return
        try:
            self._last = source.reformat(width=self._stream.width, height=self._stream.height, format="yuv420p")
            self._encode(self._last)
        except Exception as exc:
            self._error = f"encoding frame {self._frames}: {exc}"

    def repeat(self) -> None:
        if self._stream is None or self._error is not None:
            return
        try:
            if self._last is None:
                import av  # noqa: PLC0415

                black = self._np.zeros((self._stream.height, self._stream.width, 3), self._np.uint8)
                self._last = av.VideoFrame.from_ndarray(black, format="rgb24").reformat(format="yuv420p")
            self._encode(self._last)
        except Exception as exc:
            self._error = f"encoding frame {self._frames}: {exc}"

    def _encode(self, picture: Any) -> None:
        picture.pts = self._frames  # the encoder refs the picture with this pts when it is sent
        for packet in self._stream.encode(picture):
            self._container.mux(packet)
        self._frames += 1

    def finish(self) -> tuple[Any, ...]:
        if self._error is None and self._stream is not None:
            try:
                for packet in self._stream.encode():
                    self._container.mux(packet)
                self._container.close()
                fd = os.open(self._path, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
            except Exception as exc:
                self._error = f"finishing {self._path}: {exc}"
        self._container = self._stream = None
        if self._error is not None:
            return ("error", self._error)
        return ("finished", self._frames)

    def abort(self) -> tuple[Any, ...]:
        self._close_quietly()
        return ("aborted",)

    def _close_quietly(self) -> None:
        if self._container is not None:
            with contextlib.suppress(Exception):
                self._container.close()
        self._container = self._stream = None


def serve(stdin: IO[bytes], stdout: IO[bytes], ring_name: str, slot_bytes: int) -> None:
    """Encode what the parent sends until end of input."""
    from multiprocessing import shared_memory  # noqa: PLC0415

    try:
        ring = shared_memory.SharedMemory(name=ring_name, track=False)  # type: ignore[call-arg]
    except TypeError:  # Python < 3.13: attach, then stop the resource tracker from unlinking it at exit
        from multiprocessing import resource_tracker  # noqa: PLC0415

        ring = shared_memory.SharedMemory(name=ring_name)
        resource_tracker.unregister(ring._name, "shared_memory")  # type: ignore[attr-defined]
    encoder = _Encoder(ring, slot_bytes)
    try:
        while (message := read_message(stdin)) is not None:
            kind = message[0]
            if kind == "frame":
                encoder.frame(*message[1:])
            elif kind == "repeat":
                encoder.repeat()
            elif kind == "open":
                encoder.open(*message[1:])
            elif kind == "finish":
                write_message(stdout, encoder.finish())
            elif kind == "abort":
                write_message(stdout, encoder.abort())
    finally:
        encoder.abort()
        del encoder
        ring.close()


def main() -> int:
    """Entry point: ``parent_pid ring_name slot_bytes``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    parent = int(sys.argv[1])
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:
        return 0
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its banner to stderr unless told errors only
    os.nice(NICENESS)
    serve(sys.stdin.buffer, sys.stdout.buffer, sys.argv[2], int(sys.argv[3]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
