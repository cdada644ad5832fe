"""Dual Pixel views from raw and their exposure ratio, the reference: half-size RGB planes of the main and
auxiliary mosaics, white balance, ``other = main - aux``, and the DP / sharp ratio of mean signal.

A readable version of :func:`dp5k_process.rawimage.dp_views`, :func:`~dp5k_process.rawimage.half_size_rgb` and
``dp5k_process.pipeline._exposure_ratio``; the package's versions (planes converted one by one, in-place white
balance, the unsaturated mask computed once) must give the same views and ratio bit for bit
(``tests/process/test_reference_equivalence.py``). Not a test module.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError, StageError
from dp5k_common.rawfile import DualPixelFrames
from dp5k_process.rawimage import _quad_offsets


def unsaturated(img: NDArray[np.float32]) -> NDArray[np.bool_]:
    """(H, W) True where no channel of ``img`` (H, W, 3), 1.0 = white, reaches 0.98."""
    return img.max(-1) < 0.98


def exposure_ratio(dp_main: NDArray[np.float32], sharp_main: NDArray[np.float32]) -> float:
    """Ratio of mean signal DP / sharp over pixels unsaturated in both (blur preserves the mean)."""
    ok = unsaturated(dp_main) & unsaturated(sharp_main)
    if ok.mean() < 0.5:
        ok = np.ones(ok.shape, bool)
    s = float(sharp_main[ok].sum())
    if s <= 0:
        raise StageError("the sharp f/22 frame is black; cannot match its exposure")
    return float(dp_main[ok].sum()) / s


def half_size_rgb(mosaic: NDArray, black: float, cfa: str = "RGGB") -> NDArray[np.float32]:
    """(H/2, W/2, 3) float32 linear camera RGB in raw counts above black (no white balance)."""
    m = np.asarray(mosaic, dtype=np.float32)
    H, W = m.shape
    m = m[: H - H % 2, : W - W % 2]
    off = _quad_offsets(cfa)
    ch = []
    for c in "RGB":
        planes = [m[dy::2, dx::2] for dy, dx in off[c]]
        ch.append(sum(planes) / len(planes) - np.float32(black))
    return np.stack(ch, -1)


def dp_views(frames: DualPixelFrames, aux_view: str = "left") -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """(main, left, right) white-balanced linear RGB (H/2, W/2, 3), 1.0 = white - black of the main frame."""
    scale = np.float32(1.0 / (frames.white_level - frames.black_level))
    wb = np.asarray(frames.wb_gains, np.float32)
    main = half_size_rgb(frames.main, frames.black_level, frames.cfa_pattern) * wb * scale
    aux = half_size_rgb(frames.aux, frames.black_level, frames.cfa_pattern) * wb * scale
    other = main - aux
    if aux_view == "left":
        return main, aux, other
    if aux_view == "right":
        return main, other, aux
    raise BadInputError(f"aux_view must be 'left' or 'right', got {aux_view!r}")
