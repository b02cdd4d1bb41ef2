"""Test material for recordings: frames that carry their own number, readable back after lossy video coding."""

from __future__ import annotations

import numpy as np

BITS = 16
GRID = 4  # 4 x 4 blocks, one bit each


def numbered_pixels(number: int, width: int = 64, height: int = 48) -> np.ndarray:
    """An ``[height, width, 3]`` uint8 image whose 4x4 blocks spell ``number`` in binary (white = 1)."""
    image = np.zeros((height, width, 3), np.uint8)
    bh, bw = height // GRID, width // GRID
    for bit in range(BITS):
        if number >> bit & 1:
            r, c = divmod(bit, GRID)
            image[r * bh : (r + 1) * bh, c * bw : (c + 1) * bw] = 255
    return image


def read_number(image: np.ndarray) -> int:
    """The number spelled by :func:`numbered_pixels`, read from the centre of each block."""
    height, width = image.shape[:2]
    bh, bw = height // GRID, width // GRID
    number = 0
    for bit in range(BITS):
        r, c = divmod(bit, GRID)
        centre = image[r * bh + bh // 2, c * bw + bw // 2]
        if float(np.mean(centre)) > 127:
            number |= 1 << bit
    return number
