"""Camera-projector triangulation where the other camera cannot see: the projector self-calibrated from stereo.

Camera-camera matching (3DUNDERWORLD) needs a surface point seen by both cameras. A point hidden from the
other camera (behind a nearer object, or outside its field of view) still has a decoded projector code in the
reference camera, and the projector is a second "camera" whose ray through that code meets the reference ray.
The projector is not calibrated by the ChArUco shots, but every stereo-triangulated pixel is a 3D point
(reference frame, metres) with a known projector pixel, i.e. a 3D-2D correspondence. From these the projector
is calibrated as a pinhole camera: linear DLT (Hartley-normalised) for the start, decomposed into K, R, C,
then refined by ``cv2.calibrateCamera`` (intrinsic guess, zero skew, k1 only: a projector's narrow field
barely constrains k2), one round of rejecting
correspondences far off the model. The points must span depth (a single plane does not fix K); otherwise no
model is returned and only stereo depth is used.
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
        seed: seed of the subset.
    """

    min_points: int = 2000
    max_points: int = 20000
    min_flatness: float = 0.05
    max_rms_px: float = 3.0
    reject_px: float = 2.0
    seed: int = 0


@dataclass
class ProjectorModel:
    """The projector as a pinhole camera in the reference camera's frame.

    Attributes:
        calib: K, dist (projector pixels, full scale) and the projector size (W, H).
        R, T: ``X_proj = R X_ref + T`` (T metres).
        rms_px: reprojection RMS of the kept correspondences (projector pixels); n_points: how many.
    """

    calib: CameraCalibration
    R: NDArray[np.float64]
    T: NDArray[np.float64]
    rms_px: float
    n_points: int


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
    K0, _, _, _, _, _, _ = cv2.decomposeProjectionMatrix(P)
    K0 = K0 / K0[2, 2]
    K0[0, 1] = 0.0
    if not (np.isfinite(K0).all() and K0[0, 0] > 0 and K0[1, 1] > 0):
        return None
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    K, dist = K0.copy(), np.zeros(5)
    for _ in range(2):
        try:
            _, K, dist, rv, tv = cv2.calibrateCamera([X.astype(np.float32)], [x.astype(np.float32)], proj_size,
                                                     K.copy(), dist.copy(), flags=flags, criteria=crit)
        except cv2.error:
            return None
        proj = cv2.projectPoints(X, rv[0], tv[0], K, dist)[0].reshape(-1, 2)
        err = np.linalg.norm(proj - x, axis=1)
        keep = err <= max(cfg.reject_px, 3.0 * float(np.median(err)))
        if keep.all() or keep.sum() < cfg.min_points:
            break
        X, x = X[keep], x[keep]
    rms = float(np.sqrt(np.mean(err[keep] ** 2)))
    if rms > cfg.max_rms_px:
        return None
    R = cv2.Rodrigues(rv[0])[0]
    return ProjectorModel(CameraCalibration(K, dist.ravel(), tuple(proj_size)), R, tv[0].ravel(), rms, int(keep.sum()))


def procam_depth(ref_rays: NDArray[np.float32], ref_fx_px: float, proj_u: NDArray[np.float32],
                 proj_v: NDArray[np.float32], ok: NDArray[np.bool_], model: ProjectorModel,
                 cfg: TriangulationConfig = TriangulationConfig()) -> NDArray[np.float32]:
    """Depth z (metres, NaN invalid) on the reference grid from the reference ray and the projector ray.

    Args:
        ref_rays: (H, W, 2) reference normalised coordinates; ref_fx_px its focal length (px).
        proj_u, proj_v: (H, W) sub-pixel projector coordinates (full scale) of each reference pixel.
        ok: (H, W) pixels to triangulate. Column and row codes over-determine the depth; the two rays must
            pass within ``cfg.max_gap_px`` reference pixels of each other (an epipolar check).
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
