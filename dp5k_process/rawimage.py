"""Linear images from Dual Pixel RAW frames: half-size demosaic (one output pixel per 2x2 Bayer quad).

Equivalent to LibRaw's ``half_size`` demosaic with ``output_color=raw``, no gamma and no auto-brightness: per
2x2 RGGB quad, R, mean(G1, G2), B, minus black, times the white-balance gains, divided by
``white - black`` (so 1.0 = the raw white level of the *main* frame). The left/right views are
``aux`` and ``main - aux`` (after black subtraction, each frame carries its own black offset).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError
from dp5k_common.rawfile import DualPixelFrames



def _quad_offsets(cfa: str) -> dict[str, list[tuple[int, int]]]:
    if len(cfa) != 4 or sorted(cfa) != ["B", "G", "G", "R"]:
        raise BadInputError(f"unsupported CFA pattern {cfa!r} (need a 2x2 Bayer pattern such as RGGB)")
    out: dict[str, list[tuple[int, int]]] = {"R": [], "G": [], "B": []}
    for i, c in enumerate(cfa):
        out[c].append(divmod(i, 2))
    return out


def half_size_rgb(mosaic: NDArray, black: float, cfa: str = "RGGB") -> NDArray[np.float32]:
    """(H/2, W/2, 3) float32 linear camera RGB in raw counts above black (no white balance).

    Per channel ``sum(planes) / len(planes) - black`` in float32, each plane converted from the mosaic on its
    own (no float32 copy of the whole mosaic) and written into the output (no ``np.stack``)."""
    m = np.asarray(mosaic)
    H, W = m.shape
    m = m[: H - H % 2, : W - W % 2]
    off = _quad_offsets(cfa)
    out = np.empty(((H - H % 2) // 2, (W - W % 2) // 2, 3), np.float32)
    blk = np.float32(black)
    for k, c in enumerate("RGB"):
        planes = [m[dy::2, dx::2].astype(np.float32) for dy, dx in off[c]]
        acc = planes[0]
        for p in planes[1:]:
            acc += p
        if len(planes) > 1:
            acc /= len(planes)
        np.subtract(acc, blk, out=out[..., k])
    return out


def dp_views(frames: DualPixelFrames, aux_view: str = "left") -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """(main, left, right) white-balanced linear RGB (H/2, W/2, 3), 1.0 = white - black of the main frame."""
    scale = np.float32(1.0 / (frames.white_level - frames.black_level))
    wb = np.asarray(frames.wb_gains, np.float32)
    main = half_size_rgb(frames.main, frames.black_level, frames.cfa_pattern)
    aux = half_size_rgb(frames.aux, frames.black_level, frames.cfa_pattern)
    for a in (main, aux):  # a * wb * scale, in place
        a *= wb
        a *= scale
    other = main - aux
    if aux_view == "left":
        return main, aux, other
    if aux_view == "right":
        return main, other, aux
    raise BadInputError(f"aux_view must be 'left' or 'right', got {aux_view!r}")


def resize_image(img: NDArray[np.float32], size: tuple[int, int]) -> NDArray[np.float32]:
    """Area resize (linear images) to (W, H); identity when already that size."""
    if (img.shape[1], img.shape[0]) == tuple(size):
        return img
    return cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA)
