"""Statistical outlier removal on an organised cloud (a depth map): Open3D's statistic, neighbours on the pixel grid.

Open3D's ``remove_statistical_outlier(k, std_ratio)`` (paper [21]) gives every point the mean distance to its k
nearest neighbours in 3D (itself included, at 0 m), and keeps the points whose mean lies below
``mean + std_ratio * std`` of all means (Bessel-corrected). A depth map is an organised cloud: a pixel's nearest
3D neighbours on a surface are its neighbours on the pixel grid, so here the k - 1 nearest are chosen among the
``window_px`` x ``window_px`` grid neighbours (48 for 7 x 7; the 19 nearest on a frontal surface are the
pixels within sqrt(5) px, and a pixel beside a depth step still has 27 on its own side). No KD-tree, cost
linear in the pixels:

* when fewer than k - 1 neighbours in the window are valid (a speck, a corner), each missing one counts at
  ``(window_px // 2 + 1)`` pixel footprints (``z`` x the ray spacing, metres): the nearest a point outside the
  window can be on a frontal surface;
* the cloud's mean and std come from the pixels of a regular grid of every n-th row and column, n chosen so
  that about ``STATS_SAMPLE_PX`` valid pixels are sampled (all of them on small maps; exact per pixel);
* a pixel is kept without selecting when an upper bound of its mean already passes: the mean over the
  symmetric set of nearest grid offsets ``F`` (|F| >= k - 1; 20 for k = 20) less its largest distance bounds
  the mean of the k - 1 smallest, so ``(k - 1) (sum_F - max_F) / (|F| - 1) / k < threshold`` keeps it. The
  rest (depth edges, holes, flying pixels and the noisiest pixels: 1-30 % of them, more where the depth noise
  is larger than the pixel footprint) get the exact selection (``np.partition``).

The result differs from Open3D's only where the true 3D neighbours lie outside the window or on another part of
the cloud; ``benchmarks/bench_process.py`` and ``tests/process/test_grid_outliers.py`` measure by how much.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

STATS_SAMPLE_PX = 50_000
"""Valid pixels the cloud's mean and std are estimated from (standard error of the mean ~0.5 % of the std)."""
EXACT_CHUNK_PX = 65536
"""Pixels per chunk of the exact selection (keeps its (3, chunk, 48) stack at ~40 MB)."""


def window_offsets(window_px: int) -> NDArray[np.int64]:
    """(n, 2) grid offsets (dy, dx) of a ``window_px`` x ``window_px`` window without (0, 0), nearest first."""
    r = window_px // 2
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    off = np.column_stack([dy.ravel(), dx.ravel()])
    off = off[(off != 0).any(1)]
    return off[np.argsort((off ** 2).sum(1), kind="stable")]


def bound_offsets(window_px: int, n_select: int) -> NDArray[np.int64]:
    """Half (dy > 0, or dy == 0 and dx > 0) of the symmetric set of grid offsets within the smallest radius that
    holds at least ``n_select`` offsets: each distance computed once serves both of its pixels."""
    off = window_offsets(window_px)
    r2 = (off ** 2).sum(1)
    radius2 = np.sort(r2)[n_select - 1]
    near = off[r2 <= radius2]
    return near[(near[:, 0] > 0) | ((near[:, 0] == 0) & (near[:, 1] > 0))]


def organised_points(depth_m: NDArray[np.float32], rays: NDArray[np.float32]) -> NDArray[np.float32]:
    """(3, H, W) float32 points in metres, ``X = z (x_n, y_n, 1)``; NaN where the depth is invalid."""
    z = depth_m.astype(np.float32)
    return np.stack([rays[..., 0] * z, rays[..., 1] * z, z])


def _shifted_pair(P: NDArray[np.float32], dy: int, dx: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Slices ``a``, ``b`` of an (.., H, W) array with ``b`` = ``a`` moved by (dy, dx) (dy >= 0)."""
    H, W = P.shape[-2:]
    ys_a, ys_b = slice(0, H - dy), slice(dy, H)
    xs_a, xs_b = (slice(0, W - dx), slice(dx, W)) if dx >= 0 else (slice(-dx, W), slice(0, W + dx))
    return (ys_a, xs_a), (ys_b, xs_b)


BOUND_BLOCK_PX = 32768
"""Pixels (whole rows) per block of :func:`bound_sum_m`: the points, sums and maxima of a block stay in the CPU
caches across its offsets instead of a full-image pass per offset."""


def bound_sum_m(P: NDArray[np.float32], offsets: NDArray[np.int64], block_px: int = BOUND_BLOCK_PX
                ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(H, W) sum and largest of the 3D distances (metres) to the neighbours at ``offsets`` and their mirror
    images; NaN where one of them is invalid or outside the image.

    Row block by row block; within a block the offsets come in the same order and each pixel adds its distance
    to ``p + offset`` before the one to ``p - offset``, as a whole-image pass per offset does, so the float32
    sums are the same. A distance between two blocks' pixels is computed in both blocks."""
    H, W = P.shape[1:]
    ry, rx = int(offsets[:, 0].max()), int(np.abs(offsets[:, 1]).max())
    S = np.full((H, W), np.nan, np.float32)
    S[ry:H - ry, rx:W - rx] = 0.0  # pixels whose every offset lies inside the image
    M = np.zeros((H, W), np.float32)
    rows = max(1, int(block_px) // max(W, 1))
    offs = [(int(dy), int(dx)) for dy, dx in offsets]
    for y0 in range(0, H, rows):
        y1 = min(H, y0 + rows)
        for dy, dx in offs:
            r0, r1 = max(0, y0 - dy), min(H - dy, y1)  # rows of the pairs' first pixels that touch the block
            if r1 <= r0:
                continue
            (_, xa), (_, xb) = _shifted_pair(P, dy, dx)
            diff = P[:, r0:r1, xa] - P[:, r0 + dy:r1 + dy, xb]
            d = np.sqrt(np.einsum("ijk,ijk->jk", diff, diff))
            a0, a1 = max(r0, y0), r1  # first pixels inside the block
            if a1 > a0:
                S[a0:a1, xa] += d[a0 - r0:a1 - r0]
                np.fmax(M[a0:a1, xa], d[a0 - r0:a1 - r0], out=M[a0:a1, xa])
            b0, b1 = r0, min(r1, y1 - dy)  # second pixels (row + dy) inside the block
            if b1 > b0:
                S[b0 + dy:b1 + dy, xb] += d[b0 - r0:b1 - r0]
                np.fmax(M[b0 + dy:b1 + dy, xb], d[b0 - r0:b1 - r0], out=M[b0 + dy:b1 + dy, xb])
    return S, M


def pad_points(P: NDArray[np.float32], window_px: int) -> NDArray[np.float32]:
    """``P`` with a NaN border of ``window_px // 2`` pixels (what :func:`exact_mean_distance_m` indexes)."""
    r = window_px // 2
    H, W = P.shape[1:]
    pad = np.full((P.shape[0], H + 2 * r, W + 2 * r), np.nan, P.dtype)
    pad[:, r:r + H, r:r + W] = P
    return pad


def exact_mean_distance_m(P: NDArray[np.float32], ys: NDArray[np.int64], xs: NDArray[np.int64], n_select: int,
                          window_px: int, missing_px: float, ray_step: float,
                          padded: NDArray[np.float32] | None = None) -> NDArray[np.float64]:
    """Mean distance (metres) of the pixels (ys, xs) to their ``n_select`` nearest window neighbours and themselves
    (the self distance 0 counts: divided by ``n_select + 1``, as Open3D does); where fewer than ``n_select``
    neighbours are valid, each missing one counts at ``missing_px`` footprints of the pixel. ``padded``:
    :func:`pad_points` of ``P`` when already made (the filter selects twice from one padded copy)."""
    r = window_px // 2
    pad = pad_points(P, window_px) if padded is None else padded
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
    padded = pad_points(P, window_px)
    avg = exact_mean_distance_m(P, ys, xs, n_select, window_px, missing_px, ray_step, padded)
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
        avg = exact_mean_distance_m(P, ys, xs, n_select, window_px, missing_px, ray_step, padded)
        bad = ~((avg > 0) & (avg < threshold_m))
        remove[ys[bad], xs[bad]] = True
    return remove
