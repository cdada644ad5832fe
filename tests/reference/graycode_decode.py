"""Gray-code decoding, the reference: one camera's captured pattern set to per-pixel projector column and row codes.

A readable version of :func:`dp5k_process.graycode.decode_graycode`, streamed bit by bit over whole images with
plain numpy and OpenCV box filters; the package's version (uint16 codes, in-place bit tests, raw counts without
float copies) must give the same decode bit for bit (``tests/process/test_reference_equivalence.py``). Slow by
design: do not optimise it. Not a test module.
"""

from __future__ import annotations

from typing import Callable, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError
from dp5k_process.graycode import GrayCodeConfig, GrayDecode, _as_float, n_bits, n_patterns


def decode_graycode(
    patterns: Sequence[NDArray] | Callable[[int], NDArray],
    white: NDArray,
    black: NDArray,
    full_scale: float,
    cfg: GrayCodeConfig = GrayCodeConfig(),
) -> GrayDecode:
    """Decode one camera's captured Gray-code set, streaming bit by bit (two images in memory at a time).

    Args:
        patterns: the ``n_patterns`` captured images in OpenCV order, as a sequence or a loader ``i -> image``;
            each (H, W), any real dtype (8-bit, 16-bit, float; linear or not: only pos/neg order and
            differences are used).
        white, black: (H, W) captures of the all-white and all-black projections.
        full_scale: the images' full-scale value (255 for 8-bit, white level - black level for raw).
        cfg: settings.

    Returns:
        The decode; see :class:`GrayDecode`.
    """
    load = patterns if callable(patterns) else (lambda i: patterns[i])
    n_expected = n_patterns(cfg.proj_width, cfg.proj_height)
    if not callable(patterns) and len(patterns) != n_expected:
        raise BadInputError(f"expected {n_expected} Gray-code images for a {cfg.proj_width}x{cfg.proj_height} "
                            f"projector, got {len(patterns)}")
    w = _as_float(white)
    b = _as_float(black)
    squares = [n for n in (int(cfg.denoise_px), int(cfg.denoise_wide_px)) if n > 1]
    L = int(cfg.denoise_line_px)

    def box(a: NDArray[np.float32], size: tuple[int, int]) -> NDArray[np.float32]:
        return cv2.boxFilter(a, -1, size, borderType=cv2.BORDER_REFLECT)

    wb = w - b
    contrast = np.abs(wb)
    lit = contrast > cfg.black_thr * full_scale
    thr = np.maximum(np.float32(cfg.white_thr * full_scale), np.float32(cfg.rel_thr) * contrast)
    # per axis: (box size, its bit threshold), finest first; a mean over m pixels has 1/sqrt(m) of the noise
    levels: list[list[tuple[tuple[int, int], NDArray[np.float32]]]] = [[], []]
    order: list[int] = squares[:1] + ([-L] if L > 1 else []) + squares[1:]  # the lines after the first square
    for n in order:
        if n < 0:  # lines along the stripes
            for axis, size in enumerate(((1, L), (L, 1))):  # (width, height): along column / row stripes
                c = np.abs(box(wb, size))
                levels[axis].append((size, np.maximum(np.float32(cfg.white_thr * full_scale / np.sqrt(L)),
                                                      np.float32(cfg.rel_thr) * c)))
            continue
        contrast_s = np.abs(box(wb, (n, n)))
        lit |= contrast_s > cfg.black_thr * full_scale / n
        t = np.maximum(np.float32(cfg.white_thr * full_scale / n), np.float32(cfg.rel_thr) * contrast_s)
        for axis in (0, 1):
            levels[axis].append(((n, n), t))
    out = []
    offset = 0
    for axis, nb in enumerate((n_bits(cfg.proj_width), n_bits(cfg.proj_height))):
        code = np.zeros(w.shape, np.int32)
        prev = np.zeros(w.shape, np.bool_)
        weak = np.zeros(w.shape, np.uint8)
        count = np.zeros(w.shape, np.uint8)
        for k in range(nb):
            pos = _as_float(load(offset + 2 * k))
            neg = _as_float(load(offset + 2 * k + 1))
            if pos.shape != w.shape or neg.shape != w.shape:
                raise BadInputError(f"pattern {offset + 2 * k} has shape {pos.shape}, expected {w.shape}")
            diff = pos - neg
            strong = np.abs(diff) >= thr
            bit = diff > 0
            for size, t in levels[axis]:  # the finest level with a clear decision gives the bit
                diff_s = box(diff, size)
                strong_s = np.abs(diff_s) >= t
                if cfg.agree_px:
                    strong_s &= (diff_s > 0) == (diff > 0)
                bit = np.where(strong, bit, diff_s > 0)
                strong |= strong_s
            weak += ~strong
            count += weak <= cfg.max_weak_bits
            prev ^= bit  # Gray -> binary: b_k = b_{k-1} xor g_k
            code = (code << 1) | prev
        out.append((code, count))
        offset += 2 * nb
    (col, cb), (row, rb) = out
    return GrayDecode(col, row, cb, rb, lit, cfg)
