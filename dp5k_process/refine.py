"""Stereo extrinsics checked against the structured-light matches, and refined when they do not fit the scene.

The Gray code matches the two cameras without any calibration (pixels with the same projector code), so a scene
gives tens of thousands of correspondences. With the right extrinsics every such pair of rays meets; the
triangulation keeps a match only when the rays pass within ``TriangulationConfig.max_gap_px`` (1.5 px) of each
other. A rig whose geometry moved after the ChArUco shots (a knocked tripod, focus breathing) or a calibration
file from another session fails that test for most matches, and depth coverage collapses without any other sign.

So every scene is checked at the probe scale (the finest whose projector pixel spans at least one camera pixel),
and when the gate keeps fewer than ``RefineConfig.trigger_pass_rate`` of the matches:

1. correspondences: a seeded subset of the matched cam0 pixels and their sub-pixel matches in cam1, undistorted
   with the calibration's intrinsics (kept as they are);
2. starts: the given extrinsics, and the essential matrix by RANSAC (``cv2.findEssentialMat`` on normalised
   coordinates) with ``cv2.recoverPose``; the one with the lower robust cost is kept;
3. robust least squares (``scipy.optimize.least_squares``, soft-L1) of the Sampson epipolar distance in pixels over
   **three** parameters: the rotations about the baseline and about the optical axis, and the baseline's tilt
   across it (vertical, for a horizontal rig). These move points *across* their epipolar lines, which is what
   the ray-gap test sees and what the matches determine. The other two (the rotation about the axis
   perpendicular to the baseline and the optical axis, yaw for a horizontal rig, and the baseline's forward tilt)
   move points *along* the epipolar lines: they act like a disparity offset, the matches constrain them only
   through the perspective at the image corners, and their own sub-pixel biases decide them. Refining them too
   left the studio's knocked rig 0.15 deg off in yaw and its depth 3 % off; held at the ChArUco values, a camera
   turned about its own axes is recovered to 0.01 deg (docs/processing.md);
4. the five-parameter fit is used instead only when the three cannot make the matches fit, or when it explains
   them clearly better (median epipolar error below ``release_ratio`` of the three's: the held directions are then
   off, as after a turn with yaw in it), and then only if it makes ``free_pass_rate`` of the matches pass and the
   matched points are not one plane (on a plane more than one pose explains them).

**Metric scale.** Epipolar geometry fixes only the direction of the baseline; its length stays the ChArUco
calibration's ``|T|`` (the board's squares are metric). A knocked camera turns far more than it moves: a 4 deg
turn moves image points by 7 % of the focal length, while 1 mm on a 0.3 m baseline is 0.3 % of depth; that
residual scale error is not observable from the scene and remains.

A refinement is used only if it makes enough matches pass the gate; the report carries both calibrations, both
coverages, the epipolar errors and the warnings (:func:`refine_stereo`, :func:`check_and_refine`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.calibrate import CameraCalibration, StereoCalibration, rotation_angle_deg
from dp5k_common.io import finite_json

from .graycode import GrayDecode
from .triangulate import (
    CentroidMap,
    CodeView,
    camera_px_per_projector_px,
    centroid_map,
    TriangulationConfig,
    code_view,
    depth_from_match,
    match_in_other,
    midpoint_triangulate,
)

log = logging.getLogger(__name__)

ViewCache = dict[tuple[str, int], CodeView | CentroidMap]
"""(camera, scale) -> that camera's code view at that scale, shared by the steps of one scene; (camera +
``CENTROIDS_KEY``, scale) -> its centroid map where only that was needed (:func:`cached_centroids`)."""
CENTROIDS_KEY = "/centroids"


def cached_view(decs: dict[str, GrayDecode], cam: str, scale: int, tri: TriangulationConfig,
                cache: ViewCache | None) -> CodeView:
    """``cam``'s code view at ``scale``, taken from ``cache`` or computed and stored there (None: computed).

    One cache must only ever see the same ``decs`` and ``tri``."""
    if cache is None:
        return code_view(*decs[cam].at_scale(scale), decs[cam].scale_size(scale), tri, scale)
    if (cam, scale) not in cache:
        cm = cache.pop((cam + CENTROIDS_KEY, scale), None)
        cache[(cam, scale)] = code_view(*decs[cam].at_scale(scale), decs[cam].scale_size(scale), tri, scale,
                                        centroids=cm)
    view = cache[(cam, scale)]
    assert isinstance(view, CodeView)
    return view


def cached_centroids(decs: dict[str, GrayDecode], cam: str, scale: int, cache: ViewCache | None
                     ) -> CodeView | CentroidMap:
    """``cam``'s bucket centroids at ``scale`` (what :func:`~.triangulate.match_in_other` uses of its ``coarse``
    view): the cached code view when there is one, else a :class:`CentroidMap`, taken from ``cache`` or computed
    and stored there; a later :func:`cached_view` of the same camera and scale reuses it."""
    if cache is None:
        return centroid_map(*decs[cam].at_scale(scale), decs[cam].scale_size(scale), scale)
    if (cam, scale) in cache:
        return cache[(cam, scale)]
    key = (cam + CENTROIDS_KEY, scale)
    if key not in cache:
        cache[key] = centroid_map(*decs[cam].at_scale(scale), decs[cam].scale_size(scale), scale)
    return cache[key]


@dataclass(frozen=True)
class RefineConfig:
    """When and how the stereo extrinsics are refined, and when the report warns.

    Attributes:
        fit: refine when triggered; False only checks (a misfit is then reported as ``failed``).
        trigger_pass_rate: refine when fewer than this fraction of the decoded matches pass the ray-gap test.
        trigger_epipolar_px: ... or when their median epipolar error (Sampson distance, px, with the given
            calibration) is above this. The gate alone (1.5 px) lets a drift of a degree or two pass: cam1 turned by
            1.5 deg of yaw and 0.5 of roll keeps 88 % of the matches in the gate and puts depth 25 % off, at a median
            epipolar error of 0.41 px on a 320 px camera (more on larger ones); a rig that fits its matches gives 0.1-0.2 px.
        fail_epipolar_px: a refined calibration that still leaves a median epipolar error above this is reported as
            not fitting (``failed``); between ``trigger_epipolar_px`` and this, a warning (the real statue capture
            refines to 0.40 and 0.56 px with a file whose own stereo RMS was 0.81 px, and its depth then agrees with
            OpenCV's self-calibration to 0.07 and 0.7 %).
        trigger_systematic_px: ... or when the smooth part of those errors across the image
            (:func:`systematic_px`) is above this: on a small camera a drift's errors are within the decoding noise
            in the median, but they are systematic and noise is not (0.34 against 0.01 px on the synthetic rig).
        warn_pass_rate: warn when, in the end, fewer than this fraction pass (the calibration still does not fit).
        warn_rotation_deg: warn when the refinement rotated the stereo geometry by more than this (degrees).
        warn_direction_deg: warn when it turned the baseline direction by more than this (degrees).
        max_points: correspondences used (a seeded random subset above this).
        ransac_px: RANSAC inlier threshold of the essential matrix, and the scale of the soft-L1 loss (px).
        min_points: fewest correspondences to refine from.
        min_flatness: the five-parameter fallback is used only when the matched points, triangulated with it, are
            not a plane: the ratio of the 3rd to the 1st singular value of the centred points must reach this (the
            projector self-calibration's rule). Matches on one plane leave the extrinsics ambiguous: on the
            kamino410 wall two homography decompositions fit them to 0.24 and 0.30 px median.
        free_pass_rate: ... and only when it makes at least this fraction of the matches pass the ray-gap test: it
            frees the two directions the matches barely constrain, so it must fit clearly to be believed.
        release_ratio: the five-parameter fit is tried when the three-parameter one leaves the matches unfitted
            (below ``trigger_pass_rate``) or when its median epipolar error is below this fraction of the
            three-parameter one (the held directions are then off, e.g. a turn with yaw in it), or when the
            three-parameter one leaves more than ``trigger_epipolar_px``. On the knocked studio rig without yaw the
            ratio is 0.998; with 1 deg of yaw 0.91.
        free_max_depth_sd_pct: ... and used only where the scene pins its two extra parameters: the standard
            deviation they leave on the depth scale (the robust fit's covariance of the rotation about the held axis
            and the baseline's forward tilt, propagated through the median log-depth of the matches; percent) must
            stay below this. A scene without depth structure (one plane, a narrow field) leaves them free, and the
            fit then moves them on noise. This is the formal (noise) uncertainty: sub-pixel biases of the matches
            along the epipolar lines are not in it.
        seed: seed of the subset and of RANSAC's sampling.
    """

    fit: bool = True
    trigger_pass_rate: float = 0.5
    trigger_epipolar_px: float = 0.5
    trigger_systematic_px: float = 0.2
    fail_epipolar_px: float = 1.0
    warn_pass_rate: float = 0.5
    warn_rotation_deg: float = 0.5
    warn_direction_deg: float = 2.0
    max_points: int = 20000
    ransac_px: float = 1.0
    min_points: int = 200
    min_flatness: float = 0.05
    free_pass_rate: float = 0.8
    release_ratio: float = 0.95
    free_max_depth_sd_pct: float = 1.0
    seed: int = 0


@dataclass
class Matches:
    """Camera-camera correspondences through the projector code (cam0 is the reference).

    Attributes:
        x0, x1: (N, 2) pixel coordinates in cam0 and cam1 (distorted, as captured).
        scale: the projector scale exponent they were matched at.
        n_pixels: cam0's pixel count (coverage denominator).
    """

    x0: NDArray[np.float64]
    x1: NDArray[np.float64]
    scale: int
    n_pixels: int


def probe_scale(decs: dict[str, GrayDecode], tri: TriangulationConfig, cache: ViewCache | None = None) -> int:
    """The finest projector scale whose pixel spans at least one cam0 pixel (the coarsest if none)."""
    fp = camera_px_per_projector_px(cached_view(decs, "cam0", 0, tri, cache))
    n = decs["cam0"].cfg.n_scales
    return next((s for s in range(n) if np.isfinite(fp) and fp * (1 << s) >= 1.0), n - 1)


def sl_matches(decs: dict[str, GrayDecode], tri: TriangulationConfig, scale: int | None = None,
               cache: ViewCache | None = None) -> Matches:
    """Sub-pixel cam0 -> cam1 matches through the projector code (no calibration involved); code views from and
    into ``cache`` (:func:`cached_view`)."""
    s = probe_scale(decs, tri, cache) if scale is None else scale
    views = {cam: cached_view(decs, cam, s, tri, cache) for cam in ("cam0", "cam1")}
    q, ok = match_in_other(views["cam0"], views["cam1"], tri)
    ys, xs = np.nonzero(ok)
    return Matches(np.column_stack([xs, ys]).astype(np.float64), q[ok].astype(np.float64), s, ok.size)


def procam_matches(dec: GrayDecode, tri: TriangulationConfig, scale: int = 0) -> Matches:
    """Camera -> projector correspondences of a camera-projector rig: every decoded camera pixel and its sub-pixel
    projector coordinate (full scale; the smoothed code of :func:`code_view`). With the projector as ``cam1`` of a
    :class:`StereoCalibration`, :func:`check_and_refine` checks and refines the camera-projector extrinsics."""
    col, row, valid = dec.at_scale(scale)
    v = code_view(col, row, valid, dec.scale_size(scale), tri, scale)
    ok = valid & np.isfinite(v.u) & np.isfinite(v.v)
    ys, xs = np.nonzero(ok)
    proj = np.column_stack([v.to_full(v.u)[ok], v.to_full(v.v)[ok]])
    return Matches(np.column_stack([xs, ys]).astype(np.float64), proj.astype(np.float64), scale, ok.size)


def _normalised(x: NDArray[np.float64], cam: CameraCalibration) -> NDArray[np.float64]:
    return cv2.undistortPoints(x.reshape(-1, 1, 2), cam.K, cam.dist).reshape(-1, 2)


def gate_stats(m: Matches, st: StereoCalibration, tri: TriangulationConfig) -> tuple[float, float]:
    """(pass rate: fraction of the matches whose rays meet within the gate, coverage: those / cam0's pixels)."""
    if len(m.x0) == 0:
        return 0.0, 0.0
    rays = np.zeros((1, len(m.x0), 2), np.float32)
    rays[0] = _normalised(m.x0, st.cam0)
    depth = depth_from_match(rays, float(st.cam0.K[0, 0]), m.x1.reshape(1, -1, 2).astype(np.float32),
                             np.ones((1, len(m.x0)), bool), st.cam1, st.R, st.T, tri)
    n_ok = int(np.isfinite(depth).sum())
    return n_ok / len(m.x0), n_ok / m.n_pixels


def flatness(x0: NDArray[np.float64], x1: NDArray[np.float64], st: StereoCalibration) -> float:
    """How far the points triangulated from x0 <-> x1 with ``st`` are from one plane: the robust spread (normalised
    MAD) along their least principal axis over that along the largest (0 = a plane). Robust, because mismatches
    at depth edges would otherwise make a wall look thick."""
    a = np.column_stack([_normalised(x0, st.cam0), np.ones(len(x0))])
    b = np.column_stack([_normalised(x1, st.cam1), np.ones(len(x1))])
    X = midpoint_triangulate(a, b, st.R, np.asarray(st.T, np.float64).ravel())[0]
    X = X[np.isfinite(X).all(1)]
    if len(X) < 10:
        return 0.0
    med = np.median(X, 0)
    X = X[(np.abs(X - med) <= 5 * 1.4826 * np.median(np.abs(X - med), 0) + 1e-12).all(1)]
    if len(X) < 10:
        return 0.0
    axes = np.linalg.svd(X - np.median(X, 0), full_matrices=False)[2]
    proj = (X - np.median(X, 0)) @ axes.T
    spread = 1.4826 * np.median(np.abs(proj - np.median(proj, 0)), 0)
    return float(spread[2] / spread[0]) if spread[0] > 0 else 0.0


def sampson_px(n0: NDArray[np.float64], n1: NDArray[np.float64], R: NDArray[np.float64], T: NDArray[np.float64],
               f_px: float) -> NDArray[np.float64]:
    """Signed Sampson epipolar distance (pixels at focal length ``f_px``) of normalised correspondences."""
    t = np.asarray(T, np.float64).ravel()
    t = t / np.linalg.norm(t)
    E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    x0 = np.column_stack([n0, np.ones(len(n0))])
    x1 = np.column_stack([n1, np.ones(len(n1))])
    Ex0 = x0 @ E.T
    Etx1 = x1 @ E
    num = np.einsum("ij,ij->i", x1, Ex0)
    den = np.sqrt(Ex0[:, 0] ** 2 + Ex0[:, 1] ** 2 + Etx1[:, 0] ** 2 + Etx1[:, 1] ** 2)
    return f_px * num / np.maximum(den, 1e-12)


def held_axes(d: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Unit vectors in cam1's frame for a baseline direction ``d``: ``u = d``, ``n = u x z`` perpendicular to the
    baseline and cam1's optical axis ``z`` (vertical for a horizontal rig) and ``m = u x n`` (towards ``z``)."""
    u = np.asarray(d, np.float64).ravel() / np.linalg.norm(d)
    n = np.cross(u, np.array([0.0, 0.0, 1.0]))
    n /= np.linalg.norm(n)
    return u, n, np.cross(u, n)


def refine_extrinsics(x0: NDArray[np.float64], x1: NDArray[np.float64], cam0: CameraCalibration,
                      cam1: CameraCalibration, R0: NDArray[np.float64], T0: NDArray[np.float64],
                      cfg: RefineConfig = RefineConfig()) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
    """Extrinsics (R, T: ``X1 = R X0 + T``, |T| = |T0| metres) that best explain pixel correspondences x0 <-> x1,
    changed from (R0, T0) only where epipolar geometry determines them (module docstring).

    Three parameters, in cam1's frame, with the axes ``u, n, m`` of the refined baseline (:func:`held_axes`):
    rotations about ``u`` and ``m`` (R = exp(alpha u + gamma m) R0) and the baseline's tilt towards ``n`` (T = |T0|
    (d0 + b n) / norm, d0 = T0 / |T0|). Held at the ChArUco values: the rotation about ``n`` and the baseline's
    component along ``m``, which move points along their epipolar lines. The axes follow the refined baseline (a
    few fixed-point rounds), so that a camera turned about its own axes keeps its rotation about ``n`` at zero
    whatever the turn did to the baseline's direction. Intrinsics are held. Returns R, T and numbers for the report
    (the start used, RANSAC inliers, epipolar errors in px) with, under ``"free"``, the fit of all five parameters
    (its R and T, and how far it moved the held directions): the fallback when the three cannot explain the matches.
    """
    from scipy.optimize import least_squares

    n0, n1 = _normalised(x0, cam0), _normalised(x1, cam1)
    f_px = 0.5 * float(cam0.K[0, 0] + cam1.K[0, 0])
    T0 = np.asarray(T0, np.float64).ravel()
    base = float(np.linalg.norm(T0))
    d0 = T0 / base
    axes = held_axes(d0)

    def unpack(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """p = (alpha, gamma, b), optionally (+ rotation about n, tilt along m) for the free fit."""
        u, n, m = axes
        q = np.r_[p, np.zeros(5 - len(p))]
        t = d0 + q[2] * n + q[4] * m
        return cv2.Rodrigues(q[0] * u + q[1] * m + q[3] * n)[0] @ R0, base * t / np.linalg.norm(t)

    def pack(R: NDArray[np.float64], T: NDArray[np.float64]) -> NDArray[np.float64]:
        """The five parameters of a pose (the tilt offsets to first order, exact for unit-norm poses near d0)."""
        u, n, m = axes
        w = cv2.Rodrigues(R @ R0.T)[0].ravel()
        d = np.asarray(T, np.float64).ravel() / np.linalg.norm(T)
        d = d / (d @ d0)  # on the tangent plane at d0
        return np.r_[w @ u, w @ m, (d - d0) @ n, w @ n, (d - d0) @ m]

    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return sampson_px(n0, n1, *unpack(p), f_px)

    def robust_cost(p: NDArray[np.float64]) -> float:
        r = resid(p) / cfg.ransac_px
        return float(np.sum(2 * (np.sqrt(1 + r * r) - 1)))

    def solve(p: NDArray[np.float64]) -> Any:
        return least_squares(resid, p, loss="soft_l1", f_scale=cfg.ransac_px, x_scale=np.full(len(p), 1e-3),
                             max_nfev=200)

    def fit(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return solve(p).x

    starts: list[tuple[str, NDArray[np.float64]]] = [("charuco", np.zeros(5))]
    cv2.setRNGSeed(cfg.seed)
    E, inl = cv2.findEssentialMat(n0, n1, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=cfg.ransac_px / f_px)
    n_inl = 0
    if E is not None and E.shape == (3, 3):
        n_inl, Re, te, _ = cv2.recoverPose(E, n0, n1, np.eye(3), mask=inl.copy())
        if float(te.ravel() @ d0) > 0.2:  # the same side as the ChArUco baseline, within ~80 deg
            starts.append(("essential matrix", pack(Re, te.ravel())))
    name, p = min(starts, key=lambda s: robust_cost(s[1][:3]))
    p = p[:3]
    for _ in range(3):  # the held axes follow the refined baseline
        R, T = unpack(p := fit(p))
        w = cv2.Rodrigues(R @ R0.T)[0].ravel()
        axes = held_axes(T)
        p = np.r_[w @ axes[0], w @ axes[2], ((T / base) - d0) @ axes[1]]
    p = fit(p)
    # all five parameters, from the best of the starts and the three-parameter solution
    free_res = solve(min([np.r_[p, 0.0, 0.0]] + [s[1] for s in starts], key=robust_cost))
    free = free_res.x
    R, T = unpack(p)
    Rf, Tf = unpack(free)
    before = np.abs(resid(np.zeros(3)))
    # how well the scene pins the free fit's two extra parameters: their formal standard deviations (robust
    # Gauss-Newton covariance) and what they leave of the depth scale (the covariance through d median log z / dp)
    J = np.asarray(free_res.jac, np.float64)
    dof = max(len(n0) - len(free), 1)
    try:
        cov = np.linalg.inv(J.T @ J) * (2.0 * float(free_res.cost) / dof)
        held_sd = np.degrees(np.sqrt(np.clip(np.diag(cov)[3:5], 0, None)))
        sub = np.linspace(0, len(n0) - 1, min(len(n0), 4000)).astype(int)
        a, b = (np.column_stack([n[sub], np.ones(len(sub))]) for n in (n0, n1))
        z = midpoint_triangulate(a, b, *unpack(free))[0][:, 2]
        grad = []
        for k in (3, 4):
            step = np.zeros(5)
            step[k] = 1e-4
            zk = midpoint_triangulate(a, b, *unpack(free + step))[0][:, 2]
            ok = (z > 0) & (zk > 0)
            grad.append(float(np.median(np.log(zk[ok] / z[ok]))) / 1e-4 if ok.any() else np.inf)
        g = np.array(grad)
        depth_sd_pct = 100 * float(np.sqrt(max(g @ cov[3:5, 3:5] @ g, 0.0))) if np.isfinite(g).all() else float("inf")
    except np.linalg.LinAlgError:
        held_sd, depth_sd_pct = np.array([np.inf, np.inf]), float("inf")
    info = {"start": name, "ransac_inliers": int(n_inl), "points": len(n0),
            "epipolar_error_px_before": float(np.median(before)),
            "epipolar_error_px_after": float(np.median(np.abs(resid(p)))),
            "epipolar_p90_px_after": float(np.percentile(np.abs(resid(p)), 90)),
            "held_axis_cam1": axes[1].round(4).tolist(),
            "free": {"R": Rf, "T": Tf, "epipolar_error_px": float(np.median(np.abs(resid(free)))),
                     "epipolar_p90_px": float(np.percentile(np.abs(resid(free)), 90)),
                     "rotation_about_held_axis_deg": float(np.degrees(free[3])),
                     "baseline_tilt_forward_deg": float(np.degrees(np.arctan(free[4]))),
                     "held_sd_deg": [float(v) for v in held_sd], "depth_sd_pct": depth_sd_pct}}
    return R, T, info


def _pose_json(R: NDArray[np.float64], T: NDArray[np.float64]) -> dict[str, Any]:
    rv = cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()
    return {"rotation_vector_deg": np.degrees(rv).round(4).tolist(), "T_m": np.asarray(T, float).ravel().round(6).tolist(),
            "R": np.asarray(R, float).round(8).tolist()}


def refine_stereo(decs: dict[str, GrayDecode], st: StereoCalibration, tri: TriangulationConfig,
                  cfg: RefineConfig | None = RefineConfig(), where: str = "", cache: ViewCache | None = None
                  ) -> tuple[StereoCalibration, dict[str, Any], list[str]]:
    """Check the ChArUco extrinsics against the structured-light matches; refine them when the ray-gap test rejects
    most matches (module docstring). Code views come from and go into ``cache`` (:func:`cached_view`), for the
    depth step to reuse.

    Returns:
        the calibration to triangulate with (the input, or a copy with refined R, T and its rectification),
        the report's ``refinement`` object, and warnings (one line each, also logged).
    """
    if cfg is None:
        return st, {"enabled": False}, []
    return check_and_refine(sl_matches(decs, tri, cache=cache), st, tri, cfg, where)


def epipolar_px(m: Matches, idx: NDArray[np.intp], st: StereoCalibration) -> NDArray[np.float64]:
    """Signed Sampson epipolar distance (px at the cameras' mean focal length) of the matches ``idx`` under ``st``."""
    f_px = 0.5 * float(st.cam0.K[0, 0] + st.cam1.K[0, 0])
    return sampson_px(_normalised(m.x0[idx], st.cam0), _normalised(m.x1[idx], st.cam1), st.R, st.T, f_px)


def systematic_px(x0: NDArray[np.float64], err: NDArray[np.float64], size: tuple[int, int]) -> float:
    """Median |smooth part| of the signed epipolar errors ``err`` over camera 0's image: a least-squares quadratic
    in the (W, H)-normalised positions ``x0`` (px; outliers beyond 5 MAD left out). A turned camera leaves such a
    field (roll: linear in x; pitch: constant plus y^2; yaw: x y), noise does not: 0.01 px on the synthetic rig's
    true calibration and 0.34 px after 1.5 deg of yaw and 0.5 of roll, whose median error (0.41 px) is not far above
    what decoding noise alone gives a small camera (0.18 px)."""
    if len(err) < 12:
        return float("nan")
    u, v = x0[:, 0] / size[0] - 0.5, x0[:, 1] / size[1] - 0.5
    A = np.column_stack([np.ones_like(u), u, v, u * v, u * u, v * v])
    dev = np.abs(err - np.median(err))
    ok = dev <= 5 * 1.4826 * np.median(dev) + 1e-12
    coef = np.linalg.lstsq(A[ok], err[ok], rcond=None)[0]
    return float(np.median(np.abs(A @ coef)))


def match_z_m(m: Matches, idx: NDArray[np.intp], st: StereoCalibration) -> NDArray[np.float64]:
    """z in camera 0 (metres, ray midpoint) of the matches ``idx`` under ``st``."""
    n0 = np.column_stack([_normalised(m.x0[idx], st.cam0), np.ones(len(idx))])
    n1 = np.column_stack([_normalised(m.x1[idx], st.cam1), np.ones(len(idx))])
    return midpoint_triangulate(n0, n1, st.R, np.asarray(st.T, np.float64).ravel())[0][:, 2]


def _depth_ratio(m: Matches, idx: NDArray[np.intp], a: StereoCalibration, b: StereoCalibration) -> float:
    """Median z under ``b`` / z under ``a`` of the matches ``idx``: how much the choice between two calibrations
    changes the depth."""
    za, zb = match_z_m(m, idx, a), match_z_m(m, idx, b)
    ok = np.isfinite(za) & np.isfinite(zb) & (za > 0) & (zb > 0)
    return float(np.median(zb[ok] / za[ok])) if ok.any() else float("nan")


def check_and_refine(m: Matches, st: StereoCalibration, tri: TriangulationConfig, cfg: RefineConfig = RefineConfig(),
                     where: str = "") -> tuple[StereoCalibration, dict[str, Any], list[str]]:
    """:func:`refine_stereo` on given correspondences: ``m.x0`` in ``st.cam0``, ``m.x1`` in ``st.cam1`` (which may be
    a projector, for a camera-projector rig).

    The report's ``refinement`` always gives the gate's pass rate, the median and p90 epipolar error of the matches
    and its systematic part, with the given calibration (``*_given``) and the one used; when refined, both fits
    (``three_parameters``, ``five_parameters``: pose, epipolar errors, gate pass rate; the five's flatness, the
    formal standard deviations of its two extra parameters and the depth-scale uncertainty they leave, whether it
    was used and why not; ``free_fit`` repeats the five's numbers under their earlier name); ``failed`` (with
    ``failed_why``) when the calibration used does not fit the matches; ``match_depth_m``, the matches' depths.
    """
    rate0, cov0 = gate_stats(m, st, tri)
    idx = np.arange(len(m.x0))
    if len(idx) > cfg.max_points:
        idx = np.sort(np.random.default_rng(cfg.seed).choice(len(idx), cfg.max_points, replace=False))
    signed0 = epipolar_px(m, idx, st) if len(idx) else np.array([np.nan])
    epi0, sys0 = np.abs(signed0), systematic_px(m.x0[idx], signed0, st.cam0.image_size)
    info: dict[str, Any] = {"enabled": True, "probe_scale": f"1/{1 << m.scale}", "matches": len(m.x0),
                            "gate_px": tri.max_gap_px, "gate_pass_rate_charuco": rate0, "stereo_coverage_charuco": cov0,
                            "epipolar_error_px_given": float(np.median(epi0)),
                            "epipolar_p90_px_given": float(np.percentile(epi0, 90)),
                            "epipolar_systematic_px_given": sys0,
                            "charuco": _pose_json(st.R, st.T), "applied": False, "failed": False,
                            "triggered": bool(rate0 < cfg.trigger_pass_rate or np.median(epi0) > cfg.trigger_epipolar_px
                                              or sys0 > cfg.trigger_systematic_px)}
    warnings: list[str] = []
    out, rate, cov = st, rate0, cov0
    if info["triggered"] and not cfg.fit:
        info["failed"], info["failed_why"] = True, "the calibration does not fit the images (not refined: --no-refine)"
        warnings.append(f"the stereo calibration does not fit the structured light (median epipolar error "
                        f"{np.median(epi0):.2f} px, its systematic part {sys0:.2f} px, {100 * rate0:.1f} % of the matches "
                        f"in the {tri.max_gap_px:g} px ray gap) and was not refined: the depth may be off")
    elif info["triggered"] and len(m.x0) >= cfg.min_points:
        R, T, rinfo = refine_extrinsics(m.x0[idx], m.x1[idx], st.cam0, st.cam1, st.R, st.T, cfg)
        free = rinfo.pop("free")

        def candidate(Rc: NDArray[np.float64], Tc: NDArray[np.float64]) -> StereoCalibration:
            c = replace(st, R=Rc, T=np.asarray(Tc, float).ravel())
            c.rectify()
            return c

        three = candidate(R, T)
        rate3, cov3 = gate_stats(m, three, tri)
        epi3 = rinfo["epipolar_error_px_after"]
        info["flatness"] = flatness(m.x0[idx], m.x1[idx], three)
        tried = [("three parameters", three, rate3, cov3, epi3)]
        info["three_parameters"] = {**_pose_json(R, T), "epipolar_error_px": epi3,
                                    "epipolar_p90_px": rinfo["epipolar_p90_px_after"], "gate_pass_rate": rate3}
        # the held directions are released when the three cannot make the matches fit, or when releasing them
        # explains the matches clearly better (the held directions are then off: a turn with yaw in it)
        held_off = free["epipolar_error_px"] < cfg.release_ratio * epi3
        five_used, why_not = False, "not needed: the three parameters explain the matches as well"
        if rate3 < cfg.trigger_pass_rate or epi3 > cfg.trigger_epipolar_px or held_off:
            five = candidate(free["R"], free["T"])
            free["flatness"] = flatness(m.x0[idx], m.x1[idx], five)
            rate5, cov5 = gate_stats(m, five, tri)
            free["gate_pass_rate"] = rate5
            free["depth_ratio_five_to_three"] = _depth_ratio(m, idx, three, five)
            sd = free["depth_sd_pct"]
            if free["flatness"] < cfg.min_flatness:  # on a plane more than one pose explains the matches
                why_not = (f"the matches lie on one plane (flatness {free['flatness']:.3f} below {cfg.min_flatness:g}), "
                           f"which more than one pose explains")
            elif not sd <= cfg.free_max_depth_sd_pct:
                why_not = (f"the scene does not pin its two extra parameters (they leave the depth scale uncertain by "
                           f"{sd:.2f} %, above {cfg.free_max_depth_sd_pct:g} %)")
            elif not (rate5 >= cfg.free_pass_rate or (rate3 < cfg.trigger_pass_rate and rate5 > rate3)):
                why_not = f"{100 * rate5:.1f} % of the matches pass with it (below {100 * cfg.free_pass_rate:.0f} %)"
            else:
                five_used, why_not = True, ""
                tried.insert(0, ("five parameters", five, rate5, cov5, free["epipolar_error_px"]))
        info["five_parameters"] = {**_pose_json(free["R"], free["T"]),
                                   **{k: v for k, v in free.items() if k not in ("R", "T")},
                                   "used": five_used, **({"why_not": why_not} if not five_used else {})}
        mode, cand, rate1, cov1, epi1 = tried[0]
        info.update(rinfo, gate_pass_rate_refined=rate1, stereo_coverage_refined=cov1, refined=_pose_json(cand.R, cand.T),
                    mode=mode, free_fit={k: v for k, v in free.items() if k not in ("R", "T")},
                    rotation_change_deg=rotation_angle_deg(st.R, cand.R),
                    baseline_direction_change_deg=float(np.degrees(np.arccos(np.clip(
                        np.dot(st.T.ravel(), cand.T) / (np.linalg.norm(st.T) * np.linalg.norm(cand.T)), -1, 1)))),
                    baseline_m=float(np.linalg.norm(cand.T)), gate_pass_rate_three_parameters=rate3,
                    epipolar_error_px_refined=epi1)
        need = cfg.free_pass_rate if mode == "five parameters" else cfg.trigger_pass_rate
        if rate1 >= need and (rate1 > rate0 or epi1 < info["epipolar_error_px_given"]):
            out, rate, cov = cand, rate1, cov1
            info["applied"] = True
            moved = (info["rotation_change_deg"] > cfg.warn_rotation_deg
                     or info["baseline_direction_change_deg"] > cfg.warn_direction_deg)
            if moved or mode == "five parameters":
                warnings.append(
                    f"the stereo calibration did not fit the structured light (median epipolar error "
                    f"{info['epipolar_error_px_given']:.2f} px): refined from the scene's own matches ({mode}, "
                    f"{epi1:.2f} px), it moved by {info['rotation_change_deg']:.2f} deg in rotation and "
                    f"{info['baseline_direction_change_deg']:.2f} deg in baseline direction (warning above "
                    f"{cfg.warn_rotation_deg:g} / {cfg.warn_direction_deg:g} deg); matches passing the "
                    f"{tri.max_gap_px:g} px ray gap {100 * rate0:.1f} % -> {100 * rate1:.1f} %. Baseline length kept "
                    f"from the calibration ({info['baseline_m']:.4f} m). Check the rig (knocked, refocused?) and the depth"
                    + ("; the rotation about the axis perpendicular to the baseline and the baseline's forward tilt "
                       f"came from the scene's perspective (they leave {free['depth_sd_pct']:.2f} % of depth-scale "
                       f"uncertainty); "
                       f"depth differs by {100 * (free['depth_ratio_five_to_three'] - 1):+.1f} % from the "
                       f"three-parameter fit ({epi3:.2f} px)" if mode == "five parameters" else "")
                    + (f"; the scene is nearly one plane (flatness {info['flatness']:.3f} below {cfg.min_flatness:g}), "
                       f"on which the pitch about the baseline and the baseline's tilt trade off: expect depth errors "
                       f"of the order of 1 %" if info["flatness"] < cfg.min_flatness else ""))
            if mode == "three parameters" and held_off:
                info["failed"] = True
                info["failed_why"] = ("the calibration does not fit the images: its yaw and forward baseline tilt are off "
                                      "and the scene cannot pin them")
                warnings.append(
                    f"REFINEMENT INCOMPLETE: the three-parameter fit holds the rotation about the axis perpendicular to "
                    f"the baseline (yaw, for a horizontal rig) and the baseline's forward tilt at the given values, but "
                    f"releasing them explains the matches clearly better ({free['epipolar_error_px']:.2f} against "
                    f"{epi3:.2f} px) and would change depth by {100 * (free.get('depth_ratio_five_to_three', 1.0) - 1):+.1f} %; "
                    f"not used because {why_not}: the depth scale may be off; calibrate the rig again")
            elif epi1 > cfg.fail_epipolar_px:
                info["failed"] = True
                info["failed_why"] = "the calibration does not fit the images: the refined one still leaves a large epipolar error"
                warnings.append(f"REFINEMENT INCOMPLETE: the refined calibration leaves a median epipolar error of "
                                f"{epi1:.2f} px (above {cfg.fail_epipolar_px:g} px): the depth may be off; calibrate "
                                f"the rig again")
            elif epi1 > cfg.trigger_epipolar_px:
                warnings.append(f"the refined calibration still leaves a median epipolar error of {epi1:.2f} px (a rig "
                                f"that fits gives 0.1-0.2 px): the intrinsics or the distortion of the file may be off")
        else:
            info["failed"] = True
            info["failed_why"] = "the calibration does not fit the images and no refinement made it fit"
            warnings.append(
                f"REFINEMENT FAILED: refining the stereo extrinsics from the structured light did not make the matches "
                f"fit (passing the {tri.max_gap_px:g} px ray gap: {100 * rate0:.1f} % -> {100 * rate1:.1f} %, median "
                f"epipolar error {info['epipolar_error_px_given']:.1f} -> {epi3:.1f} px with three parameters, "
                f"{free['epipolar_error_px']:.2f} px with five"
                + (f"; five not used: {why_not}" if not five_used and "gate_pass_rate" in free else
                   f" ({100 * rate1:.1f} % passing; not used below {100 * cfg.free_pass_rate:.0f} %)"
                   if mode == "five parameters" else "")
                + "); kept the given calibration: it is wrong beyond what this scene can correct (intrinsics? another "
                  "rig?); calibrate the rig again")
    elif info["triggered"]:
        info["failed"], info["failed_why"] = True, f"too few decoded matches ({len(m.x0)}) to check the calibration"
        warnings.append(f"too few structured-light matches ({len(m.x0)}) to check or refine the stereo calibration")
    info["gate_pass_rate"] = rate
    info["stereo_coverage"] = cov
    signed = epipolar_px(m, idx, out) if len(idx) else np.array([np.nan])
    info["epipolar_error_px"] = float(np.median(np.abs(signed)))
    info["epipolar_systematic_px"] = systematic_px(m.x0[idx], signed, st.cam0.image_size)
    z = match_z_m(m, idx, out) if len(idx) else np.zeros(0)
    z = z[np.isfinite(z)]
    info["match_depth_m"] = ({"median": float(np.median(z)), "p5": float(np.percentile(z, 5)),
                              "p95": float(np.percentile(z, 95)), "behind_camera": float(np.mean(z <= 0))}
                             if z.size else None)
    if rate < cfg.warn_pass_rate:
        warnings.append(f"LOW DEPTH COVERAGE: only {100 * rate:.1f} % of the decoded structured-light matches pass the "
                        f"{tri.max_gap_px:g} px ray-gap test (stereo coverage {100 * cov:.1f} % of the pixels at scale "
                        f"{info['probe_scale']}; warning below {100 * cfg.warn_pass_rate:.0f} %): the stereo calibration "
                        f"does not fit these images")
    for w in warnings:
        log.warning("%s%s", f"{where}: " if where else "", w)
    return out, finite_json(info), warnings
