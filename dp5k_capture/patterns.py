"""The structured-light projections: OpenCV contrib Gray code at the projector's full resolution.

Projection ``k < 2 (ceil(log2 W) + ceil(log2 H))`` is ``cv2.structured_light.GrayCodePattern`` pattern ``k``
(column bits then row bits, MSB first, each followed by its inverse); the last two are all white and all
black. At 1920 x 1200 that is 44 + 2 = 46 projections (docs/data-format.md). Coarser projector scales use
the most significant bit pairs of this one set; nothing more is projected.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np
from numpy.typing import NDArray


@functools.lru_cache(maxsize=2)
def gray_code_patterns(width: int, height: int) -> tuple[NDArray[np.uint8], ...]:
    """The Gray-code patterns, uint8 (height, width) with values 0/255, in OpenCV's order."""
    gen = cv2.structured_light.GrayCodePattern.create(int(width), int(height))
    ok, patterns = gen.generate()
    if not ok:
        raise RuntimeError(f"OpenCV could not generate Gray-code patterns for {width}x{height}")
    return tuple(np.asarray(p, dtype=np.uint8) for p in patterns)


def projection_count(width: int, height: int) -> int:
    """Number of projections: Gray-code patterns (positive and negative) + white + black.

    >>> projection_count(1920, 1200)
    46
    """
    bits = int(np.ceil(np.log2(width))) + int(np.ceil(np.log2(height)))
    return 2 * bits + 2


def projection(k: int, width: int, height: int) -> NDArray[np.uint8]:
    """Projection ``k``: Gray code pattern ``k``, or white (``n-2``) / black (``n-1``); uint8 (height, width)."""
    n = projection_count(width, height)
    if not 0 <= k < n:
        raise IndexError(f"projection {k} out of range 0..{n - 1}")
    if k == n - 2:
        return np.full((height, width), 255, np.uint8)
    if k == n - 1:
        return np.zeros((height, width), np.uint8)
    return gray_code_patterns(width, height)[k]


def projection_label(k: int, width: int, height: int) -> str:
    """Human-readable name of projection ``k`` (e.g. ``col bit 0 +``, ``white``)."""
    n = projection_count(width, height)
    cols = int(np.ceil(np.log2(width)))
    if k == n - 2:
        return "white"
    if k == n - 1:
        return "black"
    bit, neg = divmod(k, 2)
    axis, idx = ("col", bit) if bit < cols else ("row", bit - cols)
    return f"{axis} bit {idx} {'-' if neg else '+'}"
