"""Stereo depth from structured light, the reference: code views, matching in the other camera, ray-midpoint
triangulation.

A readable version of the depth step's algorithms in :mod:`dp5k_process.triangulate`:

* :func:`bucket_centroids_px`, :func:`sample_centroids` and :func:`code_view`: per projector pixel the mean camera
  pixel (3DUNDERWORLD's bucket), smoothed codes and their gradients;
* :func:`match_in_other`: for every reference pixel the sub-pixel point of the other camera with the same code
  (a start from the centroids, then Newton steps on the smoothed codes), over the whole image at once;
* :func:`midpoint_depth` and :func:`depth_from_match`: depth by the midpoint of the two rays, in one pass.

The package's versions (one blurred mask for both codes, reusable centroid maps, matching in row blocks,
triangulation in chunks) must give the same views, matches and depths bit for bit
(``tests/process/test_reference_equivalence.py``). Not a test module.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.calibrate import CameraCalibration
from dp5k_process.triangulate import CodeView, TriangulationConfig, _remap, smooth_code, undistort_px


def bucket_centroids_px(
    col: NDArray[np.int32], row: NDArray[np.int32], valid: NDArray[np.bool_], proj_size: tuple[int, int]
) -> tuple[NDArray[np.float32], int]:
    """Mean pixel position (x, y) of the camera pixels of each projector pixel, (Hp, Wp, 2), NaN where none,
    and the number of distinct projector pixels seen.

    This is 3DUNDERWORLD's bucket, averaged instead of enumerating all pixel pairs (linear, ``np.bincount``).
    """
    Wp, Hp = proj_size
    ys, xs = np.nonzero(valid)
    idx = row[ys, xs].astype(np.int64) * Wp + col[ys, xs]
    n = np.bincount(idx, minlength=Wp * Hp).astype(np.float32)
    cen = np.empty((Hp, Wp, 2), np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        cen[..., 0] = (np.bincount(idx, weights=xs, minlength=Wp * Hp).astype(np.float32) / n).reshape(Hp, Wp)
        cen[..., 1] = (np.bincount(idx, weights=ys, minlength=Wp * Hp).astype(np.float32) / n).reshape(Hp, Wp)
    return cen, int(np.count_nonzero(n))


def sample_centroids(cen: NDArray[np.float32], u: NDArray[np.float32], v: NDArray[np.float32]
                     ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Bilinear sample of a NaN-holed centroid map at projector coordinates (u, v), weights renormalised over
    the valid neighbours. Returns (points (..., 2), weight (...)); weight 0 = no neighbour."""
    ok = np.isfinite(cen[..., 0])
    data = np.where(ok[..., None], cen, 0).astype(np.float32)
    mu, mv = np.nan_to_num(u, nan=-10).astype(np.float32), np.nan_to_num(v, nan=-10).astype(np.float32)
    num = _remap(data, mu, mv)
    den = _remap(ok.astype(np.float32), mu, mv)
    with np.errstate(invalid="ignore", divide="ignore"):
        pts = num / den[..., None]
    return pts, den


def midpoint_depth(
    xa: NDArray[np.float64], ya: NDArray[np.float64], xb: NDArray[np.float64], yb: NDArray[np.float64],
    R: NDArray[np.float64], T: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Depth z and ray gap of :func:`midpoint_triangulate` for rays given by normalised coordinates.

    The same formula written per component for rays ``(xa, ya, 1)`` in the reference camera and ``(xb, yb, 1)``
    in the other one, without the (N, 3) temporaries (about 3x faster; equal to float64 rounding).

    Args:
        xa, ya: (N,) reference normalised coordinates; xb, yb: (N,) the other camera's.
        R, T: ``X_other = R X_ref + T``, T in metres.

    Returns:
        z (N,) metres in the reference frame (NaN behind a camera), gap (N,) metres between the rays.
    """
    C = -R.T @ np.asarray(T, np.float64).ravel()  # other camera centre in the reference frame
    bx = R[0, 0] * xb + R[1, 0] * yb + R[2, 0]  # b = R^T (xb, yb, 1)
    by = R[0, 1] * xb + R[1, 1] * yb + R[2, 1]
    bz = R[0, 2] * xb + R[1, 2] * yb + R[2, 2]
    aa = xa * xa + ya * ya + 1.0
    bb = bx * bx + by * by + bz * bz
    ab = xa * bx + ya * by + bz
    aC = xa * C[0] + ya * C[1] + C[2]
    bC = bx * C[0] + by * C[1] + bz * C[2]
    det = ab * ab - aa * bb
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = (ab * bC - bb * aC) / det
        mu = (aa * bC - ab * aC) / det
    dx = lam * xa - C[0] - mu * bx
    dy = lam * ya - C[1] - mu * by
    dz = lam - C[2] - mu * bz
    gap = np.sqrt(dx * dx + dy * dy + dz * dz)
    z = 0.5 * (lam + C[2] + mu * bz)
    z[(lam <= 0) | (mu <= 0)] = np.nan
    return z, gap


def code_view(col: NDArray[np.int32], row: NDArray[np.int32], valid: NDArray[np.bool_],
              proj_size: tuple[int, int], cfg: TriangulationConfig = TriangulationConfig(), scale: int = 0) -> CodeView:
    """Smooth codes, their gradients and bucket centroids of one camera at projector scale ``2^-scale``."""
    cen, n_codes = bucket_centroids_px(col, row, valid, proj_size)
    fp = float(np.sqrt(valid.sum() / n_codes)) if n_codes else 1.0  # camera px per projector px (side)
    sigma = max(0.7, cfg.sigma_factor * fp)
    u = smooth_code(col, valid, sigma)
    v = smooth_code(row, valid, sigma)
    g = []
    for c in (u, v):
        z = np.nan_to_num(c)
        g.append(cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=3) / 8.0)
        g.append(cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=3) / 8.0)
    return CodeView(u, v, valid, cen, np.stack(g, -1), fp, scale)


def match_in_other(ref: CodeView, other: CodeView, cfg: TriangulationConfig = TriangulationConfig(),
                   coarse: CodeView | None = None) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """For every valid reference pixel, the sub-pixel point of the other camera with the same projector code.

    Start at the other camera's bucket centroid sampled at the reference's smoothed code, then Newton steps on
    the other camera's smoothed code maps: ``q <- q + J^-1 ((u, v)_ref - (u, v)_other(q))``. Where camera pixels
    are larger than this scale's projector pixels the centroid map is sparse; ``coarse`` (the other camera at a
    coarser scale, whose map is dense) then gives the start.

    Returns:
        q (H, W, 2) pixel coordinates in the other camera (NaN where unmatched), ok (H, W) bool.
    """
    if coarse is None:
        q, w = sample_centroids(other.centroids, ref.u, ref.v)
    else:
        q, w = sample_centroids(coarse.centroids, coarse.from_full(ref.to_full(ref.u)),
                                coarse.from_full(ref.to_full(ref.v)))
    ok = ref.valid & np.isfinite(ref.u) & np.isfinite(ref.v) & (w > 0) & np.isfinite(q[..., 0])
    # the other camera's code u, v and its validity in one 3-channel image: one remap per step samples all three
    # (each channel with the same bilinear weights as a remap of its own)
    codes_o = np.dstack([np.nan_to_num(other.u), np.nan_to_num(other.v),
                         (np.isfinite(other.u) & np.isfinite(other.v)).astype(np.float32)])
    ur, vr = np.nan_to_num(ref.u), np.nan_to_num(ref.v)
    step_max = 2.0 * max(1.0, other.footprint_px, 0.0 if coarse is None else coarse.footprint_px)
    qx, qy = np.ascontiguousarray(q[..., 0]), np.ascontiguousarray(q[..., 1])
    off = np.float32(-10)  # a map coordinate outside the image: samples 0 (invalid)
    for _ in range(max(1, cfg.newton_iters)):
        mx, my = np.where(ok, qx, off), np.where(ok, qy, off)
        sampled = _remap(codes_o, mx, my)
        gr = _remap(other.grads, mx, my)
        du = ur - sampled[..., 0]
        dv = vr - sampled[..., 1]
        a, b, c, d = gr[..., 0], gr[..., 1], gr[..., 2], gr[..., 3]
        det = a * d - b * c
        good = ok & (sampled[..., 2] > 0.999) & (np.abs(det) > 1e-8)
        with np.errstate(invalid="ignore", divide="ignore"):
            sx = (d * du - b * dv) / det
            sy = (-c * du + a * dv) / det
        good &= (np.abs(sx) <= step_max) & (np.abs(sy) <= step_max)
        qx = np.where(good, qx + sx, qx)
        qy = np.where(good, qy + sy, qy)
        ok = good
    # residual after the last step
    sampled = _remap(codes_o, np.where(ok, qx, off), np.where(ok, qy, off))
    res = np.hypot(ur - sampled[..., 0], vr - sampled[..., 1])
    ok &= (sampled[..., 2] > 0.999) & (res <= cfg.max_code_residual)
    q = np.stack([qx, qy], -1)
    q[~ok] = np.nan
    return q, ok


def depth_from_match(
    ref_rays: NDArray[np.float32], ref_fx_px: float, q_px: NDArray[np.float32], ok: NDArray[np.bool_],
    other: CameraCalibration, R: NDArray[np.float64], T: NDArray[np.float64],
    cfg: TriangulationConfig = TriangulationConfig(),
) -> NDArray[np.float32]:
    """Depth z (metres, NaN invalid) on the reference grid by ray-midpoint triangulation of matched pixels.

    Args:
        ref_rays: (H, W, 2) reference normalised coordinates; ref_fx_px its focal length (px).
        q_px: (H, W, 2) matched pixel in the other camera; ok (H, W) where matched.
        other: the other camera's intrinsics; R, T: ``X_other = R X_ref + T`` (metres).
    """
    H, W = ok.shape
    depth = np.full((H, W), np.nan, np.float32)
    n = int(ok.sum())
    if n == 0:
        return depth
    qn = undistort_px(q_px[ok], other)
    a = ref_rays[ok].astype(np.float64)
    z, gap = midpoint_depth(a[:, 0], a[:, 1], qn[:, 0], qn[:, 1], R, T)
    with np.errstate(invalid="ignore", divide="ignore"):
        good = np.isfinite(z) & (z > 0) & (gap / z * ref_fx_px <= cfg.max_gap_px)
    depth[ok] = np.where(good, z, np.nan)
    return depth
