"""The functions issue 22's fourth pass changed, as they were before it (commit ca9098a), kept verbatim for the
equivalence tests (``test_pass4.py``): Gray-code decoding and its raw loader, the exposure ratio, the grid outlier
filter's bound pass and exact selection, code views and the half-size DP views. Helpers the pass did not change
are imported from ``dp5k_process``. Not a test module."""

# ruff: noqa
from __future__ import annotations

from typing import Callable, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError, StageError
from dp5k_common.rawfile import DualPixelFrames
from dp5k_process.graycode import GrayCodeConfig, GrayDecode, _as_float, n_bits, n_patterns
from dp5k_process.grid_outliers import (EXACT_CHUNK_PX, STATS_SAMPLE_PX, _shifted_pair, bound_offsets,
                                        organised_points, window_offsets)
from dp5k_process.pipeline import read_main
from dp5k_process.rawimage import _quad_offsets
from dp5k_process.session import Session
from dp5k_process.triangulate import CodeView, TriangulationConfig, centroid_map, smooth_codes, CentroidMap


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



def decode_camera(session: Session, cam: str, gcfg: GrayCodeConfig) -> tuple[GrayDecode, tuple[int, int], int]:
    """Decode one camera's structured-light set from the raw mosaics (streamed file by file).

    Returns: the decode, the raw size (W, H) and the white-black range in counts.
    """
    files = session.cameras[cam].sl
    n = len(files) - 2
    white, black_level, white_level = read_main(session, files[n])
    black = read_main(session, files[n + 1])[0]
    shape = white.shape
    full = white_level - black_level

    def load(i: int) -> NDArray[np.float32]:
        main = read_main(session, files[i])[0]
        if main.shape != shape:
            raise BadInputError(f"raw size {main.shape} differs from the session's {shape}", where=files[i])
        return main.astype(np.float32)

    dec = decode_graycode(load, white.astype(np.float32), black.astype(np.float32), float(full), gcfg)
    return dec, (shape[1], shape[0]), full



def _exposure_ratio(dp_main: NDArray[np.float32], sharp_main: NDArray[np.float32]) -> float:
    """Ratio of mean signal DP / sharp over pixels unsaturated in both (blur preserves the mean)."""
    ok = (dp_main.max(-1) < 0.98) & (sharp_main.max(-1) < 0.98)
    if ok.mean() < 0.5:
        ok = np.ones(ok.shape, bool)
    s = float(sharp_main[ok].sum())
    if s <= 0:
        raise StageError("the sharp f/22 frame is black; cannot match its exposure")
    return float(dp_main[ok].sum()) / s



def bound_sum_m(P: NDArray[np.float32], offsets: NDArray[np.int64]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(H, W) sum and largest of the 3D distances (metres) to the neighbours at ``offsets`` and their mirror
    images; NaN where one of them is invalid or outside the image."""
    H, W = P.shape[1:]
    ry, rx = int(offsets[:, 0].max()), int(np.abs(offsets[:, 1]).max())
    S = np.full((H, W), np.nan, np.float32)
    S[ry:H - ry, rx:W - rx] = 0.0  # pixels whose every offset lies inside the image
    M = np.zeros((H, W), np.float32)
    for dy, dx in offsets:
        a, b = _shifted_pair(P, int(dy), int(dx))
        diff = P[(slice(None),) + a] - P[(slice(None),) + b]
        d = np.sqrt(np.einsum("ijk,ijk->jk", diff, diff))
        S[a] += d
        S[b] += d
        np.fmax(M[a], d, out=M[a])
        np.fmax(M[b], d, out=M[b])
    return S, M


def exact_mean_distance_m(P: NDArray[np.float32], ys: NDArray[np.int64], xs: NDArray[np.int64], n_select: int,
                          window_px: int, missing_px: float, ray_step: float) -> NDArray[np.float64]:
    """Mean distance (metres) of the pixels (ys, xs) to their ``n_select`` nearest window neighbours and themselves
    (the self distance 0 counts: divided by ``n_select + 1``, as Open3D does); where fewer than ``n_select``
    neighbours are valid, each missing one counts at ``missing_px`` footprints of the pixel."""
    r = window_px // 2
    pad = np.pad(P, ((0, 0), (r, r), (r, r)), constant_values=np.nan)
    Wp = pad.shape[2]
    flat = pad.reshape(3, -1)
    off = window_offsets(window_px)
    off_flat = off[:, 0] * Wp + off[:, 1]
    out = np.empty(ys.size, np.float64)
    for i in range(0, ys.size, EXACT_CHUNK_PX):  # bounded memory
        y, x = ys[i:i + EXACT_CHUNK_PX], xs[i:i + EXACT_CHUNK_PX]
        centre = (y + r) * Wp + (x + r)
        idx = centre[:, None] + off_flat
        d2 = np.zeros(idx.shape, np.float32)
        for c in range(3):
            diff = np.take(flat[c], idx) - np.take(flat[c], centre)[:, None]
            d2 += diff * diff
        d = np.sqrt(d2)
        d[~np.isfinite(d)] = np.inf
        d = np.partition(d, n_select - 1, axis=1)[:, :n_select]
        d = np.where(np.isfinite(d), d, (missing_px * ray_step * P[2, y, x])[:, None])
        out[i:i + EXACT_CHUNK_PX] = d.sum(1, dtype=np.float64)
    return out / (n_select + 1)


def grid_outlier_mask(depth_m: NDArray[np.float32], rays: NDArray[np.float32], nb_neighbors: int = 20,
                      std_ratio: float = 2.0, window_px: int = 7) -> NDArray[np.bool_]:
    """(H, W) True at the valid pixels the statistic removes (see the module docstring).

    Args:
        depth_m: (H, W) depth in metres, NaN invalid. rays: (H, W, 2) normalised ray (x_n, y_n) per pixel.
        nb_neighbors, std_ratio: Open3D's parameters (k includes the point itself).
        window_px: odd side of the grid window the neighbours are chosen in (``window_px**2 - 1 >= k - 1``).
    """
    n_select = nb_neighbors - 1
    if window_px % 2 == 0 or window_px ** 2 - 1 < n_select:
        raise ValueError(f"window {window_px} px must be odd with at least {n_select} neighbours")
    valid = np.isfinite(depth_m)
    if valid.sum() <= nb_neighbors:
        return np.zeros(depth_m.shape, bool)
    P = organised_points(depth_m, rays)
    ray_step = float(np.median(np.abs(np.diff(rays[..., 0], axis=1))))
    missing_px = float(window_px // 2 + 1)

    stride = max(1, int(np.sqrt(valid.sum() / STATS_SAMPLE_PX)))
    sub = np.zeros_like(valid)
    sub[::stride, ::stride] = True
    ys, xs = np.nonzero(valid & sub)
    if ys.size < 2:
        ys, xs = np.nonzero(valid)
    avg = exact_mean_distance_m(P, ys, xs, n_select, window_px, missing_px, ray_step)
    avg = avg[avg > 0]
    threshold_m = avg.mean() + std_ratio * avg.std(ddof=1)

    bound = bound_offsets(window_px, n_select)
    S, M = bound_sum_m(P, bound)
    with np.errstate(invalid="ignore"):  # the n_select smallest of F without its largest, at most their mean each
        upper = (S - M) * (n_select / (2 * len(bound) - 1))
        kept_by_bound = valid & (S > 0) & (upper < nb_neighbors * threshold_m)
    ys, xs = np.nonzero(valid & ~kept_by_bound)
    remove = np.zeros(depth_m.shape, bool)
    if ys.size:
        avg = exact_mean_distance_m(P, ys, xs, n_select, window_px, missing_px, ray_step)
        bad = ~((avg > 0) & (avg < threshold_m))
        remove[ys[bad], xs[bad]] = True
    return remove


def code_view(col: NDArray[np.int32], row: NDArray[np.int32], valid: NDArray[np.bool_],
              proj_size: tuple[int, int], cfg: TriangulationConfig = TriangulationConfig(), scale: int = 0,
              centroids: CentroidMap | None = None) -> CodeView:
    """Smooth codes, their gradients and bucket centroids of one camera at projector scale ``2^-scale``
    (``centroids``: this camera's :func:`centroid_map` at this scale, when already computed)."""
    cm = centroid_map(col, row, valid, proj_size, scale) if centroids is None else centroids
    cen, fp = cm.centroids, cm.footprint_px
    sigma = max(0.7, cfg.sigma_factor * fp)
    u, v = smooth_codes(col, row, valid, sigma)
    g = []
    for c in (u, v):
        z = np.nan_to_num(c)
        g.append(cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=3) / 8.0)
        g.append(cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=3) / 8.0)
    return CodeView(u, v, valid, cen, np.stack(g, -1), fp, scale)



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
