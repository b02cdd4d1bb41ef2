"""``HighlightRing``: the last seconds of an episode held in memory, compressed, until someone asks to keep them.

A recorder in highlight mode writes nothing while an episode runs; it pushes each tick's dataset
row and camera frames into this ring, which holds at most ``capacity_rows`` of them and forgets
the oldest. Raw frames would not fit (30 s of 640x480 RGB at 30 fps is 830 MB per camera), so
each frame is compressed once, as it arrives, to a JPEG (:class:`HeldFrame`, libjpeg-turbo through
Pillow, quality 95 with 4:2:0 chroma: the dataset's video is 4:2:0 too, so the chroma it drops
the video would drop anyway) and decoded again only when a highlight is saved. What the ring holds
is counted in :attr:`HighlightRing.nbytes`: the JPEG bytes plus an estimate of each row's objects.

The ring keeps no reference to a capture buffer: a frame is read once, while :meth:`HighlightRing.push`
compresses it, so a camera may reuse or free its buffer afterwards.

Compressing costs about 3 ms per 640x480 frame. Pillow releases the interpreter lock while it
encodes only when it writes to a real file, so the ring compresses into an in-memory file
(``memfd``, Linux) and reads the bytes back: into a ``BytesIO`` the same work would hold the lock
and delay the tick thread's wake-ups by about a millisecond (measured: p50 0.6 -> 1.7 ms).

Thread-safety: one thread pushes (the recorder's worker); any thread may :meth:`~HighlightRing.snapshot`
or read the counters.
"""

from __future__ import annotations

import io
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import IO, Any, Final

import numpy as np
from PIL import Image

from openral_core import FrameEncoding, ROSRuntimeError, SensorFrame

JPEG_QUALITY: Final = 95
"""JPEG quality of held frames: far below the video codec's own loss (AV1 at CRF 30, H.264 at CRF 23)."""

MAX_HIGHLIGHT_S: Final = 600.0
"""The longest highlight a ring holds: ten minutes, at 30 fps 18 000 rows, a few GB of JPEG frames for two
640x480 cameras (30 s take 100-300 MB); longer is a continuous recording's job (``episode_every_s``)."""

_COLOUR: Final = frozenset({FrameEncoding.RGB8, FrameEncoding.BGR8, FrameEncoding.RGBA8, FrameEncoding.BGRA8})


@dataclass(frozen=True, slots=True)
class HeldFrame:
    """One camera frame held as a JPEG, with the stamps of the frame it came from."""

    sensor_id: str
    stamp_ns: int
    seq: int
    grey: bool
    jpeg: bytes

    @classmethod
    def compress(cls, frame: SensorFrame, quality: int = JPEG_QUALITY, scratch: IO[bytes] | None = None) -> HeldFrame:
        """Compress ``frame`` (8-bit colour in any channel order, or 8-bit grey); its buffer is not kept.

        ``scratch``: a real file to encode into (:func:`scratch_file`), so that the encoder runs
        without the interpreter lock; without one, a ``BytesIO``.

        Raises:
            ROSRuntimeError: A frame a dataset video cannot hold (16-bit depth, already compressed, no pixels).
        """
        if frame.encoding is FrameEncoding.MONO8 and frame.data is not None:
            pixels, grey = frame.as_array(), True
        elif frame.encoding in _COLOUR and frame.data is not None:
            pixels, grey = frame.as_rgb(), False
        else:
            raise ROSRuntimeError(
                f"camera {frame.sensor_id}: frames encoded as {frame.encoding.value} cannot be recorded as video"
            )
        image = Image.fromarray(np.ascontiguousarray(pixels))
        if scratch is None:
            out = io.BytesIO()
            image.save(out, "JPEG", quality=quality, subsampling="4:2:0")
            return cls(frame.sensor_id, frame.stamp_ns, frame.seq, grey, out.getvalue())
        scratch.seek(0)
        scratch.truncate()
        image.save(scratch, "JPEG", quality=quality, subsampling="4:2:0")
        scratch.seek(0)
        return cls(frame.sensor_id, frame.stamp_ns, frame.seq, grey, scratch.read())

    def restore(self) -> SensorFrame:
        """The frame decoded again: RGB8 (or MONO8), with its capture stamp and sequence number."""
        with Image.open(io.BytesIO(self.jpeg)) as image:
            pixels = np.asarray(image.convert("L" if self.grey else "RGB"))
        height, width = pixels.shape[:2]
        return SensorFrame(
            sensor_id=self.sensor_id,
            stamp_ns=self.stamp_ns,
            width=width,
            height=height,
            encoding=FrameEncoding.MONO8 if self.grey else FrameEncoding.RGB8,
            seq=self.seq,
            data=pixels,
        )


@dataclass(frozen=True, slots=True)
class HeldRow:
    """One tick in the ring: its dataset row (as the recorder built it) and its cameras' frames.

    A camera missing from ``frames`` had no frame that tick: the saved video repeats its previous one.
    """

    row: dict[str, Any]
    frames: dict[str, HeldFrame]
    nbytes: int


@dataclass(frozen=True, slots=True)
class Highlight:
    """What a ring held at one moment: the episode's task and its rows, oldest first."""

    task: str
    rows: list[HeldRow]


class HighlightRing:
    """The last ``capacity_rows`` rows of the episode under way, frames compressed.

    Args:
        capacity_rows: Rows held at most (the highlight's length times the dataset's fps).

    Raises:
        ValueError: ``capacity_rows`` below 1.
    """

    def __init__(self, capacity_rows: int) -> None:
        if capacity_rows < 1:
            raise ValueError(f"capacity_rows must be at least 1, got {capacity_rows}")
        self.capacity_rows = capacity_rows
        self._rows: deque[HeldRow] = deque()
        self._task: str | None = None
        self._nbytes = 0
        self._lock = threading.Lock()
        self._scratch = scratch_file()
        self.frames_compressed = 0
        """Frames compressed since the ring was built."""
        self.compress_s = 0.0
        """Time spent compressing them, seconds."""

    @property
    def rows(self) -> int:
        """Rows held now."""
        return len(self._rows)

    @property
    def nbytes(self) -> int:
        """Bytes held now: the frames' JPEGs and an estimate of the rows' Python objects."""
        return self._nbytes

    def start(self, task: str) -> None:
        """Forget what is held and hold the rows of a new episode of ``task``."""
        with self._lock:
            self._rows.clear()
            self._nbytes = 0
            self._task = task

    def stop(self) -> None:
        """Forget what is held: the episode ended (a snapshot taken before keeps its rows)."""
        with self._lock:
            self._rows.clear()
            self._nbytes = 0
            self._task = None

    def push(self, row: dict[str, Any], frames: Mapping[str, SensorFrame | None]) -> None:
        """Hold ``row`` and each camera's frame of its tick, compressed; the oldest row goes when full.

        ``row`` is held as given (not copied): the caller hands it over. Outside an episode
        (before :meth:`start`, after :meth:`stop`) nothing is held.

        Raises:
            ROSRuntimeError: A frame that cannot be held (:meth:`HeldFrame.compress`).
        """
        if self._task is None:
            return
        started = time.perf_counter()
        held = {
            sensor_id: HeldFrame.compress(frame, scratch=self._scratch)
            for sensor_id, frame in frames.items()
            if frame is not None
        }
        self.compress_s += time.perf_counter() - started
        self.frames_compressed += len(held)
        entry = HeldRow(row, held, _row_nbytes(row) + sum(len(f.jpeg) for f in held.values()))
        with self._lock:
            self._rows.append(entry)
            self._nbytes += entry.nbytes
            while len(self._rows) > self.capacity_rows:
                self._nbytes -= self._rows.popleft().nbytes

    def close(self) -> None:
        """Forget what is held and release the scratch file. Idempotent."""
        self.stop()
        if self._scratch is not None:
            self._scratch.close()
            self._scratch = None

    def snapshot(self) -> Highlight | None:
        """What is held now (references: nothing is copied), or ``None`` when nothing is."""
        with self._lock:
            if self._task is None or not self._rows:
                return None
            return Highlight(self._task, list(self._rows))


def scratch_file() -> IO[bytes] | None:
    """An in-memory file to encode frames into (``None`` where the system has no ``memfd_create``)."""
    create = getattr(os, "memfd_create", None)
    if create is None:
        return None
    try:
        return open(create("openral-highlight", os.MFD_CLOEXEC), "w+b")  # closed by HighlightRing.close
    except OSError:
        return None


def _row_nbytes(row: Mapping[str, Any]) -> int:
    """Estimated bytes of a row's dict and values (lists counted with their items)."""
    total = sys.getsizeof(row)
    for value in row.values():
        total += sys.getsizeof(value)
        if isinstance(value, list):
            total += sum(sys.getsizeof(item) for item in value)
    return total
