"""Gray-code structured-light decoding (positive/negative pairs), multi-scale from one captured set.

Pattern layout (OpenCV contrib ``structured_light.GrayCodePattern``, MSB first): index ``2k`` is column bit k,
``2k + 1`` its inverse, for ``k < n_col_bits``; then the row bits the same way. The code is the reflected binary
Gray code, white where the Gray bit is 1.

Multi-scale (paper's projector scales 1, 1/2, 1/4, 1/8): since ``gray(x >> s) == gray(x) >> s``, the patterns of a
projector ``2^s`` times smaller shown by pixel replication are the ``n - s`` most significant bit pairs of the
full set. So one decode gives all scales: the code at scale ``2^-s`` is ``code >> s`` and it is valid where the
``n - s`` leading bits are reliable. A pixel whose fine stripes blur out keeps its coarse code (OpenCV's decoder
rejects the pixel when any single bit is weak).

Thresholds (3DUNDERWORLD / OpenCV defaults 5 and 40 for 8-bit images) are given as fractions of the images'
full scale (``full_scale`` = 255 for 8-bit, white - black level for linear raw), so they rescale to 14-bit raw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError


def n_bits(n: int) -> int:
    """Number of Gray-code bits for ``n`` projector columns or rows: ``ceil(log2 n)``."""
    return int(math.ceil(math.log2(n)))


def n_patterns(proj_width: int, proj_height: int) -> int:
    """Number of pattern images (pattern + inverse per bit), 44 for 1920 x 1200."""
    return 2 * (n_bits(proj_width) + n_bits(proj_height))


@dataclass(frozen=True)
class GrayCodeConfig:
    """Decoder settings.

    Attributes:
        proj_width, proj_height: projector resolution at scale 1 (pixels).
        white_thr: least |pos - neg| for a reliable bit, fraction of full scale (OpenCV: 5/255).
        black_thr: least |white - black| for a lit (not shadowed) pixel, fraction of full scale (OpenCV: 40/255).
        rel_thr: least |pos - neg| as a fraction of the pixel's own |white - black| (0 = off; like
            3DUNDERWORLD's auto-contrast, it makes the bit test independent of albedo).
        n_scales: number of projector scales 1, 1/2, ... decoded (paper: 4).
        max_weak_bits: weak bits tolerated among a code's leading bits (per axis). A pixel that straddles a stripe
            edge has exactly one weak bit, and since neighbouring Gray codes differ in one bit, either reading of
            it gives one of the two codes the pixel really sees; 0 = OpenCV's rule (any weak bit rejects).
        denoise_px: n > 1 adds a second test on n x n box means (noise / n, so thresholds / n): a pixel too
            noisy on its own (dim, far surfaces) takes the bit and the shadow test from its neighbourhood;
            a sharp single-pixel decision still wins, so fine stripes keep their resolution. 0 = off.
        denoise_wide_px: m > denoise_px adds a wider level (m x m box means, thresholds / m) for surfaces too
            dim even for the first; a decision at a finer level wins over it. 0 = off.
        denoise_line_px: L > 1 adds, after the first square level, means over L pixels along the stripes
            (column bits: a vertical 1 x L line, row bits a horizontal L x 1 line; noise and thresholds /
            sqrt(L)). Stripes that a surface compresses (a floor receding for the row code, a side wall for the
            column code) are finer than a square box, which averages them out, but run along these lines. 0 = off.
        agree_px: a bit decided by a neighbourhood mean counts as reliable only where the pixel's own difference
            has the same sign (weak evidence, but evidence): a pixel beside a depth edge or a shadow, whose
            neighbourhood is mostly the other surface, then does not take that surface's code.
    """

    proj_width: int = 1920
    proj_height: int = 1200
    white_thr: float = 5.0 / 255.0
    black_thr: float = 40.0 / 255.0
    rel_thr: float = 0.0
    n_scales: int = 4
    max_weak_bits: int = 1
    denoise_px: int = 0
    denoise_wide_px: int = 0
    denoise_line_px: int = 0
    agree_px: bool = False

    @classmethod
    def for_linear_raw(cls, proj_width: int = 1920, proj_height: int = 1200, max_weak_bits: int = 1) -> GrayCodeConfig:
        """Thresholds for linear 14-bit raw (fractions of white - black = 15871 counts).

        The 8-bit defaults (5 and 40 of 255) assume gamma-encoded, well-exposed images; in linear raw a
        projector that adds a few hundred counts over the ambient light is normal (the f/22 structured-light
        frames), so the thresholds are set from the sensor noise instead: shadow 0.8 % (127 counts, about
        12 sigma of a white-black difference at that level), bit 0.25 % (40 counts, about 4 sigma) and at least
        10 % of the pixel's own white-black contrast; plus the neighbourhood tests for dim surfaces: 15 px lines
        along the stripes, 5 x 5 and 11 x 11 boxes, each taken only where the pixel's own difference agrees in
        sign (``denoise_line_px``, ``denoise_px``, ``denoise_wide_px``, ``agree_px``).
        """
        return cls(proj_width, proj_height, white_thr=0.0025, black_thr=0.008, rel_thr=0.10, max_weak_bits=max_weak_bits,
                   denoise_px=5, denoise_wide_px=11, denoise_line_px=15, agree_px=True)


@dataclass
class GrayDecode:
    """One camera's decode.

    Attributes:
        col, row: (H, W) int32 binary projector column/row codes at scale 1 (only the leading reliable bits
            are meaningful).
        col_bits, row_bits: (H, W) uint8 number of leading bits with at most ``max_weak_bits`` weak ones.
        lit: (H, W) bool, |white - black| above the shadow threshold.
        cfg: the settings used.
    """

    col: NDArray[np.int32]
    row: NDArray[np.int32]
    col_bits: NDArray[np.uint8]
    row_bits: NDArray[np.uint8]
    lit: NDArray[np.bool_]
    cfg: GrayCodeConfig

    def at_scale(self, s: int) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.bool_]]:
        """Codes at projector scale ``2^-s`` (s = 0..3): (col, row, valid), (H, W) each.

        Valid pixels are lit, have their ``n - s`` leading column and row bits reliable, and a code inside the
        scaled projector (``ceil(W / 2^s)`` x ``ceil(H / 2^s)``).
        """
        ncb, nrb = n_bits(self.cfg.proj_width), n_bits(self.cfg.proj_height)
        col = self.col >> s
        row = self.row >> s
        wk, hk = -(-self.cfg.proj_width // (1 << s)), -(-self.cfg.proj_height // (1 << s))
        valid = self.lit & (self.col_bits >= ncb - s) & (self.row_bits >= nrb - s) & (col < wk) & (row < hk)
        return col, row, valid

    def scale_size(self, s: int) -> tuple[int, int]:
        """(W, H) of the projector at scale ``2^-s``."""
        return -(-self.cfg.proj_width // (1 << s)), -(-self.cfg.proj_height // (1 << s))


def _as_float(img: NDArray) -> NDArray[np.float32]:
    a = np.asarray(img)
    if a.ndim != 2:
        raise BadInputError(f"structured-light images must be single channel (H, W), got shape {a.shape}")
    return a.astype(np.float32, copy=False)


def _difference(pos: NDArray, neg: NDArray, shape: tuple[int, ...], index: int) -> NDArray[np.float32]:
    """``pos - neg`` in float32 as ``_as_float(pos) - _as_float(neg)``; integer images (raw counts) are converted
    inside the subtraction instead of as two float32 copies first (exact: every integer below 2^24 is a float32)."""
    pos, neg = np.asarray(pos), np.asarray(neg)
    if pos.shape != shape or neg.shape != shape:
        bad = pos.shape if pos.shape != shape else neg.shape
        if len(bad) != 2:
            raise BadInputError(f"structured-light images must be single channel (H, W), got shape {bad}")
        raise BadInputError(f"pattern {index} has shape {bad}, expected {shape}")
    if pos.dtype == neg.dtype and pos.dtype in (np.uint8, np.uint16, np.int16, np.int8):
        return np.subtract(pos, neg, dtype=np.float32)
    return _as_float(pos) - _as_float(neg)


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
    mw = int(cfg.max_weak_bits)
    for axis, nb in enumerate((n_bits(cfg.proj_width), n_bits(cfg.proj_height))):
        # the binary code is built in the narrowest integer type that holds its nb bits (int32 at the end)
        code = np.zeros(w.shape, np.uint16 if nb <= 16 else np.int32)
        prev = np.zeros(w.shape, np.bool_)
        weak = np.zeros(w.shape, np.uint8)
        count = np.zeros(w.shape, np.uint8)
        undecided = np.empty(w.shape, np.bool_)  # ~strong, updated in place
        dpos = np.empty(w.shape, np.bool_)
        sp = np.empty(w.shape, np.bool_)
        tmp = np.empty(w.shape, np.bool_)
        for k in range(nb):
            diff = _difference(load(offset + 2 * k), load(offset + 2 * k + 1), w.shape, offset + 2 * k)
            np.greater(diff, 0, out=dpos)
            bit = dpos.copy()
            np.greater_equal(np.abs(diff), thr, out=undecided)
            np.logical_not(undecided, out=undecided)
            for size, t in levels[axis]:  # the finest level with a clear decision gives the bit
                diff_s = box(diff, size)
                np.greater(diff_s, 0, out=sp)
                np.copyto(bit, sp, where=undecided)  # np.where(strong, bit, diff_s > 0)
                np.abs(diff_s, out=diff_s)
                np.greater_equal(diff_s, t, out=tmp)  # strong_s
                if cfg.agree_px:
                    tmp &= np.equal(sp, dpos, out=sp)
                np.logical_not(tmp, out=tmp)
                undecided &= tmp  # strong |= strong_s
            weak += undecided
            count += np.less_equal(weak, mw, out=tmp)
            prev ^= bit  # Gray -> binary: b_k = b_{k-1} xor g_k
            code <<= 1
            code |= prev
        out.append((code.astype(np.int32), count))
        offset += 2 * nb
    (col, cb), (row, rb) = out
    return GrayDecode(col, row, cb, rb, lit, cfg)


def opencv_patterns(proj_width: int, proj_height: int) -> list[NDArray[np.uint8]]:
    """The pattern images OpenCV contrib generates (for tests and the studio): uint8 (H, W) each."""
    import cv2

    gc = cv2.structured_light.GrayCodePattern.create(proj_width, proj_height)
    ok, pats = gc.generate()
    if not ok:
        raise RuntimeError("GrayCodePattern.generate failed")
    return [np.asarray(p) for p in pats]
