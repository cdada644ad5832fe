"""Camera-projector triangulation where the other camera cannot see: the projector self-calibrated from stereo.

Camera-camera matching (3DUNDERWORLD) needs a surface point seen by both cameras. A point hidden from the
other camera (behind a nearer object, or outside its field of view) still has a decoded projector code in the
reference camera, and the projector is a second "camera" whose ray through that code meets the reference ray.
The projector is not calibrated by the ChArUco shots, but every stereo-triangulated pixel is a 3D point
(reference frame, metres) with a known projector pixel, i.e. a 3D-2D correspondence. From these the projector
is calibrated as a pinhole camera: linear DLT (Hartley-normalised) for the start, decomposed into K, R, C,
then refined from that start by Levenberg-Marquardt on the reprojection error (zero skew, k1 only: a
projector's narrow field barely constrains k2), one round of rejecting correspondences far off the model. The points must span depth (a single plane does not fix K) and
pin the projector's position (formal standard deviation from the fit's covariance); otherwise no model is
returned and only stereo depth is used.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.calibrate import CameraCalibration

from .filters import valid_median
from .triangulate import TriangulationConfig, midpoint_triangulate


@dataclass(frozen=True)
class ProjectorCalibConfig:
    """Settings of the projector self-calibration.

    Attributes:
        min_points: fewest stereo points to calibrate from.
        max_points: points used (a seeded random subset above this).
        min_flatness: smallest ratio of the 3rd to the 1st singular value of the centred points (a plane is 0).
        max_rms_px: largest reprojection RMS (projector pixels, full scale) for the model to be used.
        reject_px: correspondences off the first fit by more than max(reject_px, 3 x median) are dropped.
        max_position_sd_m: largest formal standard deviation of the projector's position (the components of T,
            from the fit's covariance, metres). Points crowded on one far surface with a few elsewhere pass the
            flatness test yet leave the projector's distance and focal length trading off against each other:
            on the small studio ``boxes`` scene (93 % of the points on the wall at 7 m) T_z came out 0.2 m off
            with an RMS of 1.2 px, sd 13-15 mm, where ``demo01`` has 0.1 mm; its depth off by 1-4 %.
        depth_margin: camera-projector depth is kept only within the depth range of the points the projector was
            calibrated from (their 1st to 99th percentile), widened by this fraction on either side: a model
            fitted on far walls extrapolates badly to a near box (boxes at 672 x 448 raw, points at 2-7 m: the
            0.5 m and 1.1 m boxes came out 1.3-1.4 % off).
        seed: seed of the subset.
    """

    min_points: int = 2000
    max_points: int = 20000
    min_flatness: float = 0.05
    max_rms_px: float = 3.0
    reject_px: float = 2.0
    max_position_sd_m: float = 0.002
    depth_margin: float = 0.1
    seed: int = 0


@dataclass
class ProjectorModel:
    """The projector as a pinhole camera in the reference camera's frame.

    Attributes:
        calib: K, dist (projector pixels, full scale) and the projector size (W, H).
        R, T: ``X_proj = R X_ref + T`` (T metres).
        rms_px: reprojection RMS of the kept correspondences (projector pixels); n_points: how many.
        position_sd_m: largest formal standard deviation of the components of T (metres).
        depth_range_m: (near, far) z in the reference frame where its depth is trusted (metres).
    """

    calib: CameraCalibration
    R: NDArray[np.float64]
    T: NDArray[np.float64]
    rms_px: float
    n_points: int
    position_sd_m: float = 0.0
    depth_range_m: tuple[float, float] = (0.0, float("inf"))


def _dlt(X: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """3x4 projection matrix from (N, 3) points and (N, 2) pixels, Hartley-normalised linear least squares."""
    mX, mx = X.mean(0), x.mean(0)
    sX = np.sqrt(3) / np.mean(np.linalg.norm(X - mX, axis=1))
    sx = np.sqrt(2) / np.mean(np.linalg.norm(x - mx, axis=1))
    TX = np.diag([sX, sX, sX, 1.0]); TX[:3, 3] = -sX * mX
    Tx = np.diag([sx, sx, 1.0]); Tx[:2, 2] = -sx * mx
    Xh = np.column_stack([(X - mX) * sX, np.ones(len(X))])
    xn = (x - mx) * sx
    z = np.zeros_like(Xh)
    A = np.concatenate([np.hstack([Xh, z, -xn[:, :1] * Xh]), np.hstack([z, Xh, -xn[:, 1:] * Xh])], 0)
    P = np.linalg.svd(A, full_matrices=False)[2][-1].reshape(3, 4)
    return np.linalg.inv(Tx) @ P @ TX


def correspondence_subset(n: int, cfg: ProjectorCalibConfig = ProjectorCalibConfig()) -> NDArray[np.int64] | None:
    """The seeded subset (indices, in drawing order) of ``n`` correspondences that :func:`calibrate_projector`
    fits; None when it keeps them all (``n <= cfg.max_points``)."""
    if n <= cfg.max_points:
        return None
    return np.random.default_rng(cfg.seed).choice(n, cfg.max_points, replace=False)


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
    idx = correspondence_subset(len(X), cfg)
    if idx is not None:
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


def _unpack(params: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """K (zero skew) and dist (k1 only) from the parameter vector (rvec, tvec, fx, fy, cx, cy, k1)."""
    fx, fy, cx, cy, k1 = params[6:11]
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), np.array([k1, 0.0, 0.0, 0.0, 0.0])


def _refine(X: NDArray[np.float64], x: NDArray[np.float64], params: NDArray[np.float64]
            ) -> tuple[NDArray[np.float64] | None, NDArray[np.float64]]:
    """Levenberg-Marquardt on the reprojection error from the DLT's pose and intrinsics (analytic Jacobian of
    ``cv2.projectPoints``). Returns the parameters (None if the fit failed) and each point's error (px).

    ``cv2.calibrateCamera`` is not used here: it ignores the DLT's pose and initialises the extrinsics itself,
    which on the small studio ``boxes`` scene started it 17000 px off and it never came back (RMS 134 px)."""
    from scipy.optimize import least_squares

    def project(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        K, dist = _unpack(p)
        pts, J = cv2.projectPoints(X, p[0:3], p[3:6], K, dist)
        return pts.reshape(-1, 2), J

    def fun(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return (project(p)[0] - x).ravel()

    def jac(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return project(p)[1][:, :11]  # d/d(rvec, tvec, fx, fy, cx, cy, k1)

    try:
        res = least_squares(fun, params, jac=jac, method="lm", x_scale="jac", max_nfev=200)
    except (ValueError, cv2.error, np.linalg.LinAlgError):
        return None, np.empty(0)
    if not np.isfinite(res.x).all():
        return None, np.empty(0)
    return res.x, np.linalg.norm(res.fun.reshape(-1, 2), axis=1)


def procam_depth(ref_rays: NDArray[np.float32], ref_fx_px: float, proj_u: NDArray[np.float32],
                 proj_v: NDArray[np.float32], ok: NDArray[np.bool_], model: ProjectorModel,
                 cfg: TriangulationConfig = TriangulationConfig()) -> NDArray[np.float32]:
    """Depth z (metres, NaN invalid) on the reference grid from the reference ray and the projector ray.

    Args:
        ref_rays: (H, W, 2) reference normalised coordinates; ref_fx_px its focal length (px).
        proj_u, proj_v: (H, W) sub-pixel projector coordinates (full scale) of each reference pixel.
        ok: (H, W) pixels to triangulate. Column and row codes over-determine the depth; the two rays must
            pass within ``cfg.max_gap_px`` reference pixels of each other (an epipolar check), and the depth
            must lie in ``model.depth_range_m``.
    """
    H, W = ok.shape
    depth = np.full((H, W), np.nan, np.float32)
    ok = ok & np.isfinite(proj_u) & np.isfinite(proj_v)
    n = int(ok.sum())
    if n == 0:
        return depth
    pp = np.column_stack([proj_u[ok], proj_v[ok]]).reshape(-1, 1, 2).astype(np.float64)
    pn = cv2.undistortPoints(pp, model.calib.K, model.calib.dist).reshape(-1, 2)
    a = np.concatenate([ref_rays[ok].astype(np.float64), np.ones((n, 1))], 1)
    b = np.concatenate([pn, np.ones((n, 1))], 1)
    X, gap = midpoint_triangulate(a, b, model.R, model.T)
    z = X[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        good = np.isfinite(z) & (z > 0) & (gap / z * ref_fx_px <= cfg.max_gap_px)
        good &= (z >= model.depth_range_m[0]) & (z <= model.depth_range_m[1])  # no extrapolation in depth
    depth[ok] = np.where(good, z, np.nan)
    return depth


def mixed_codes(col: NDArray[np.int32], row: NDArray[np.int32], valid: NDArray[np.bool_], u: NDArray[np.float32],
                v: NDArray[np.float32], ksize: int = 5, tol: float = 2.0) -> NDArray[np.bool_]:
    r"""(H, W) bool: pixels whose smoothed code mixes two surfaces (a depth edge), unusable against the projector.

    On a smooth surface the code is locally linear, so its Gaussian mean equals the median of the integer codes
    around the pixel (up to the staircase, < 1 code unit). Across a depth edge the codes jump and the mean lands
    between the two surfaces while the median stays on one: :math:`\max(|\hat u - \mathrm{med}\,u|,
    |\hat v - \mathrm{med}\,v|) > \max(\mathrm{tol}, 3\,\mathrm{median})` flags it (codes in units of this scale).
    Camera-camera matching rejects such pixels itself (the other camera's codes do not fit); the projector
    ray, which has no second code map to disagree with, would turn them into flying pixels between surfaces.
    """
    mu = valid_median(np.where(valid, col, np.nan).astype(np.float32), ksize)
    mv = valid_median(np.where(valid, row, np.nan).astype(np.float32), ksize)
    with np.errstate(invalid="ignore"):
        dev = np.fmax(np.abs(u - mu), np.abs(v - mv))
    fin = np.isfinite(dev)
    if not fin.any():
        return ~fin
    return ~fin | (dev > max(tol, 3.0 * float(np.median(dev[fin]))))
