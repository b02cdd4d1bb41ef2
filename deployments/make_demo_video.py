"""Write the demo video that ``video_file.yaml`` plays, or any test video like it.

Each frame carries its own index as a 16-bit code in a strip of black and white blocks along
the top edge (most significant bit first), so a reader can check frame order, looping and
pacing from the pixels alone; :func:`read_frame_index` decodes it and survives lossy codecs.
Below the strip: a blue and a red patch of known colour (for channel-order checks), a bar that
moves one step per frame, and the index as text for people watching.

Usage (from the repository root)::

    uv run python deployments/make_demo_video.py            # deployments/media/demo_320x240.mp4
    uv run python deployments/make_demo_video.py out.mp4 --width 640 --height 480 --frames 300
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

INDEX_BITS = 16
"""Bits of the frame-index code; indices wrap at 2**16."""

CODE_HEIGHT = 16
"""Pixel rows of the code strip at the top of every frame."""

BLUE_BGR = (255, 0, 0)
RED_BGR = (0, 0, 255)

DEFAULT_PATH = Path(__file__).resolve().parent / "media" / "demo_320x240.mp4"


def patch_boxes(width: int, height: int) -> dict[str, tuple[slice, slice]]:
    """Row/column slices of the solid ``blue`` and ``red`` patches in a frame of this size."""
    top = CODE_HEIGHT + 8
    size = max(8, min(width, height) // 6)
    return {
        "blue": (slice(top, top + size), slice(8, 8 + size)),
        "red": (slice(top, top + size), slice(16 + size, 16 + 2 * size)),
    }


def make_frame(index: int, width: int, height: int) -> np.ndarray:
    """The BGR image of frame ``index``."""
    if width < 4 * INDEX_BITS or height < 3 * CODE_HEIGHT:
        raise ValueError(f"frames must be at least {4 * INDEX_BITS}x{3 * CODE_HEIGHT}, got {width}x{height}")
    frame = np.full((height, width, 3), 64, np.uint8)
    frame[:, :, 1] = np.linspace(32, 160, width, dtype=np.uint8)[None, :]  # green gradient background
    bit_width = width // INDEX_BITS
    frame[:CODE_HEIGHT] = 0
    for bit in range(INDEX_BITS):
        if (index >> (INDEX_BITS - 1 - bit)) & 1:
            frame[:CODE_HEIGHT, bit * bit_width : (bit + 1) * bit_width] = 255
    for colour, (rows, cols) in zip((BLUE_BGR, RED_BGR), patch_boxes(width, height).values(), strict=True):
        frame[rows, cols] = colour
    bar = (index * 4) % width
    frame[height // 2 :, bar : bar + max(4, width // 32)] = 255
    cv2.putText(frame, f"{index}", (8, height - 10), cv2.FONT_HERSHEY_SIMPLEX, height / 320, (255, 255, 255), 1)
    return frame


def read_frame_index(frame: np.ndarray) -> int:
    """Decode the index code of a BGR, RGB or mono frame made by :func:`make_frame`."""
    gray = frame if frame.ndim == 2 else frame.mean(axis=2)
    bit_width = frame.shape[1] // INDEX_BITS
    rows = slice(CODE_HEIGHT // 4, CODE_HEIGHT - CODE_HEIGHT // 4)
    index = 0
    for bit in range(INDEX_BITS):
        cols = slice(bit * bit_width + bit_width // 4, (bit + 1) * bit_width - bit_width // 4)
        index = (index << 1) | int(gray[rows, cols].mean() > 128)
    return index


def write_demo_video(
    path: str | Path,
    *,
    width: int = 320,
    height: int = 240,
    fps: float = 30.0,
    frames: int = 90,
) -> Path:
    """Write ``frames`` frames of :func:`make_frame` to ``path`` (MPEG-4 Part 2, ``mp4v``).

    Returns:
        The path written.

    Raises:
        RuntimeError: This OpenCV build cannot write ``mp4v`` video.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), fps, (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write mp4v video to {path}")
    try:
        for index in range(frames):
            writer.write(make_frame(index, width, height))
    finally:
        writer.release()
    return path


def main(argv: list[str] | None = None) -> None:
    """Command line: write the demo video (defaults match ``deployments/video_file.yaml``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("path", nargs="?", type=Path, default=DEFAULT_PATH)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--frames", type=int, default=90)
    args = parser.parse_args(argv)
    written = write_demo_video(args.path, width=args.width, height=args.height, fps=args.fps, frames=args.frames)
    print(f"wrote {written} ({written.stat().st_size} bytes, {args.frames} frames at {args.fps} fps)")


if __name__ == "__main__":
    main()
