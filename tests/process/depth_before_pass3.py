"""The depth step as it was before issue 22's third pass (commit a50fa0b), kept verbatim for the equivalence tests
(``test_depth_pass3.py``): code views, matching, triangulation, the projector's correspondences and
``depth_for_camera``. Helpers the pass did not change are imported from ``dp5k_process``. Not a test module."""

# ruff: noqa
from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.calibrate import CameraCalibration, StereoCalibration
from dp5k_process.filters import backproject, filter_depth, recursive_fill
from dp5k_process.graycode import GrayDecode
from dp5k_process.pipeline import ProcessConfig, fill_steps_for
from dp5k_process.projector import (ProjectorCalibConfig, ProjectorModel, _dlt, _refine, _unpack, mixed_codes,
                                    procam_depth)
from dp5k_process.triangulate import (CodeView, TriangulationConfig, _remap, normalised_rays, smooth_code,
                                      undistort_px)

ViewCache = dict


def cached_view(decs, cam, scale, tri, cache):
    """refine.cached_view as it was (full code views only), with this module's code_view."""
    if cache is None:
        return code_view(*decs[cam].at_scale(scale), decs[cam].scale_size(scale), tri, scale)
    if (cam, scale) not in cache:
        cache[(cam, scale)] = code_view(*decs[cam].at_scale(scale), decs[cam].scale_size(scale), tri, scale)
    return cache[(cam, scale)]


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


def calibrate_projector(points_m: NDArray[np.float64], proj_px: NDArray[np.float64], proj_size: tuple[int, int],
                        cfg: ProjectorCalibConfig = ProjectorCalibConfig()) -> ProjectorModel | None:
    """Projector pinhole model from stereo points and their projector pixels; None if they cannot fix it.

    Args:
        points_m: (N, 3) points in the reference camera frame, metres.
        proj_px: (N, 2) projector pixel coordinates (full scale, pixel centres at integers).
        proj_size: projector (W, H) pixels.
    """
    ok = np.isfinite(points_m).all(1) & np.isfinite(proj_px).all(1)
    X, x = points_m[ok].astype(np.float64), proj_px[ok].astype(np.float64)
    if len(X) < cfg.min_points:
        return None
    if len(X) > cfg.max_points:
        idx = np.random.default_rng(cfg.seed).choice(len(X), cfg.max_points, replace=False)
        X, x = X[idx], x[idx]
    sv = np.linalg.svd(X - X.mean(0), compute_uv=False)
    if sv[2] < cfg.min_flatness * sv[0]:
        return None
    P = _dlt(X, x)
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    K0, R0, C0 = cv2.decomposeProjectionMatrix(P)[:3]
    K0 = K0 / K0[2, 2]
    K0[0, 1] = 0.0
    if not (np.isfinite(K0).all() and K0[0, 0] > 0 and K0[1, 1] > 0 and abs(float(C0[3, 0])) > 0):
        return None
    pose = np.r_[cv2.Rodrigues(R0)[0].ravel(), -R0 @ (C0[:3, 0] / C0[3, 0])]
    params = np.r_[pose, K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2], 0.0]
    for _ in range(2):
        params, err = _refine(X, x, params)
        if params is None:
            return None
        keep = err <= max(cfg.reject_px, 3.0 * float(np.median(err)))
        Xk, xk = X[keep], x[keep]  # the fit's correspondences within the bound
        if keep.all() or keep.sum() < cfg.min_points:
            break
        X, x = Xk, xk
    rms = float(np.sqrt(np.mean(err[keep] ** 2)))
    if rms > cfg.max_rms_px:
        return None
    K, dist = _unpack(params)
    J = cv2.projectPoints(Xk, params[0:3], params[3:6], K, dist)[1][:, :11]
    try:  # covariance of the parameters: (J^T J)^-1 x residual variance
        cov = np.linalg.inv(J.T @ J) * float(np.sum(err[keep] ** 2)) / max(1, 2 * len(Xk) - 11)
    except np.linalg.LinAlgError:
        return None
    sd_T = float(np.sqrt(np.max(np.diag(cov)[3:6])))
    if not sd_T <= cfg.max_position_sd_m:
        return None
    R = cv2.Rodrigues(params[0:3])[0]
    lo, hi = np.percentile(Xk[:, 2], [1.0, 99.0])
    return ProjectorModel(CameraCalibration(K, dist, tuple(proj_size)), R, params[3:6].copy(), rms, int(keep.sum()),
                          sd_T, (float(lo) * (1.0 - cfg.depth_margin), float(hi) * (1.0 + cfg.depth_margin)))


def depth_for_camera(
    decs: dict[str, GrayDecode], ref: str, st: StereoCalibration, cfg: ProcessConfig,
    views_cache: ViewCache | None = None,
) -> tuple[NDArray[np.float32], dict[str, Any]]:
    """Depth (metres, NaN invalid) on ``ref``'s raw pixel grid: per scale match + triangulate + filter, then Eq. 3.

    Pixels the other camera cannot match (hidden from it by a nearer object, or outside its view) are
    triangulated against the projector, calibrated from this camera's stereo points (``cfg.projector``).

    ``views_cache`` (camera, scale) -> code view: pass the same dict to both cameras' calls and each camera's
    views are computed once (a camera's views serve as reference for its own depth and as the other camera
    for its partner's); it holds up to (scales used + 1) views per camera, each about 40 bytes per raw pixel.
    """
    cache: ViewCache = {} if views_cache is None else views_cache

    def view(cam: str, s: int) -> CodeView:
        return cached_view(decs, cam, s, cfg.tri, cache)

    other = "cam1" if ref == "cam0" else "cam0"
    cal = {"cam0": st.cam0, "cam1": st.cam1}
    if ref == "cam0":
        R, T = st.R, st.T
    else:
        R, T = st.R.T, -st.R.T @ st.T
    rays = normalised_rays(cal[ref])
    fx = float(cal[ref].K[0, 0])
    n_scales = decs[ref].cfg.n_scales
    coarsest = n_scales - 1
    coarse_other = view(other, coarsest)
    info: dict[str, Any] = {"per_scale_coverage": [], "per_scale_coverage_stereo": []}
    n_steps = fill_steps_for(view(ref, 0), cfg.filt.fill_steps, n_scales)
    info["fill_scales"] = [f"1/{1 << s}" for s in range(n_steps)]
    views, stereo = [], []
    for s in range(n_steps):  # scales Eq. 3 does not reach are not computed
        v_ref, v_oth = view(ref, s), view(other, s)
        q, ok = match_in_other(v_ref, v_oth, cfg.tri, coarse=coarse_other)
        views.append(v_ref)
        stereo.append(depth_from_match(rays, fx, q, ok, cal[other], R, T, cfg.tri))
    filtered = [filter_depth(d, rays, cfg.filt) for d in stereo]
    model = None
    if cfg.projector is not None:  # where the other camera cannot see: reference camera + projector
        pts, codes = [], []
        for v, d in zip(views, filtered):
            X, m = backproject(d, rays)
            pts.append(X)
            codes.append(np.column_stack([v.to_full(v.u)[m], v.to_full(v.v)[m]]))
        model = calibrate_projector(np.concatenate(pts), np.concatenate(codes), decs[ref].scale_size(0), cfg.projector)
    info["projector_rms_px"] = None if model is None else model.rms_px
    info["projector_points"] = 0 if model is None else model.n_points
    info["projector_position_sd_mm"] = None if model is None else model.position_sd_m * 1000.0
    depths = []
    for s, (v, d, f) in enumerate(zip(views, stereo, filtered)):
        info["per_scale_coverage_stereo"].append(float(np.isfinite(f).mean()))
        if model is not None:
            col, row, valid = decs[ref].at_scale(s)
            todo = v.valid & ~np.isfinite(d) & ~mixed_codes(col, row, valid, v.u, v.v)
            dp = procam_depth(rays, fx, v.to_full(v.u), v.to_full(v.v), todo, model, cfg.tri)
            f = filter_depth(np.where(np.isfinite(d), d, dp), rays, cfg.filt)
        depths.append(f)
        info["per_scale_coverage"].append(float(np.isfinite(f).mean()))
    fused = recursive_fill(depths, n_steps)
    info["coverage_raw"] = float(np.isfinite(fused).mean())
    return fused, info
