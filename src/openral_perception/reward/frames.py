"""The reward monitor's memory: a ring of recent camera frames, and the trend of a score over them."""

from __future__ import annotations

import collections
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Frame:
    """One buffered camera frame: BGR bytes, row after row."""

    stamp_ns: int
    bgr: bytes
    width: int
    height: int

    def __post_init__(self) -> None:
        if len(self.bgr) != self.width * self.height * 3:
            raise ValueError(f"{len(self.bgr)} bytes for a {self.width}x{self.height} BGR frame")


class RollingFrameBuffer:
    """The frames of the last ``window_s`` seconds (relative to the newest), at most ``max_frames``.

    Args:
        window_s: How far back the buffer reaches from its newest frame.
        max_frames: The most frames kept (the oldest go first).
        stale_after_s: :meth:`is_stale` once the newest frame is older than this.
    """

    def __init__(self, *, window_s: float, max_frames: int = 256, stale_after_s: float = 3.0) -> None:
        if window_s <= 0 or max_frames < 1 or stale_after_s <= 0:
            raise ValueError("window_s and stale_after_s must be positive and max_frames at least 1")
        self.window_s = window_s
        self.max_frames = max_frames
        self.stale_after_s = stale_after_s
        self._frames: collections.deque[Frame] = collections.deque()

    def push(self, frame: Frame) -> None:
        """Add ``frame`` (frames arrive in time order; an older one than the newest is refused)."""
        if self._frames and frame.stamp_ns < self._frames[-1].stamp_ns:
            raise ValueError(f"frame at {frame.stamp_ns} ns is older than the newest ({self._frames[-1].stamp_ns})")
        self._frames.append(frame)
        horizon = frame.stamp_ns - round(self.window_s * 1e9)
        while self._frames and (self._frames[0].stamp_ns < horizon or len(self._frames) > self.max_frames):
            self._frames.popleft()

    def window(self, seconds: float | None = None) -> list[Frame]:
        """The frames of the last ``seconds`` before the newest (at most the whole window), oldest first."""
        if not self._frames:
            return []
        span = self.window_s if seconds is None else min(seconds, self.window_s)
        horizon = self._frames[-1].stamp_ns - round(span * 1e9)
        return [frame for frame in self._frames if frame.stamp_ns >= horizon]

    def is_stale(self, now_ns: int) -> bool:
        """No frame, or the newest is older than ``stale_after_s`` at ``now_ns``."""
        return not self._frames or now_ns - self._frames[-1].stamp_ns > self.stale_after_s * 1e9

    def __len__(self) -> int:
        return len(self._frames)


def trend(series: Sequence[float]) -> float:
    """Least-squares slope per sample (0 for fewer than two samples)."""
    n = len(series)
    if n < 2:
        return 0.0
    mean_x = (n - 1) / 2
    mean_y = sum(series) / n
    numerator = sum((i - mean_x) * (y - mean_y) for i, y in enumerate(series))
    denominator = sum((i - mean_x) ** 2 for i in range(n))
    return numerator / denominator
