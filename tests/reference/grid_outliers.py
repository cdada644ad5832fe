"""Statistical outlier removal on the pixel grid, the reference: Open3D's statistic with neighbours taken in a window.

A readable version of :func:`dp5k_process.grid_outliers.grid_outlier_mask`: the bound pass over whole images (one
shifted pair per window offset) and the exact selection of every pixel it cannot clear. The package's version (the
bound pass in row blocks, one padded copy for both selections) must remove the same pixels and compute the same
sums and maxima bit for bit (``tests/process/test_reference_equivalence.py``). Not a test module.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from dp5k_process.grid_outliers import (EXACT_CHUNK_PX, STATS_SAMPLE_PX, _shifted_pair, bound_offsets,
                                        organised_points, window_offsets)


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
