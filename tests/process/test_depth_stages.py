"""Triangulation from codes, filters, Eq. 3 fill and the Eq. 5 focus estimator."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from calib.calibrate import CameraCalibration
from dp5k_common.errors import BadInputError, StageError
from dp5k_process.filters import close_holes, recursive_fill, statistical_outliers, valid_median
from dp5k_process.focus import FocusConfig, focus_distance, huber_skip_mean
from dp5k_process.graycode import GrayCodeConfig, decode_graycode, opencv_patterns
from dp5k_process.triangulate import (TriangulationConfig, code_view, depth_from_match, match_in_other,
                                      midpoint_depth, midpoint_triangulate, normalised_rays, sample_centroids,
                                      undistort_px)
from dp5k_testing.procam_synth import PlaneScene, look_at_rig, render_projection


@pytest.fixture(scope="module")
def plane_capture():
    cam0, cam1, proj = look_at_rig(f_px=400.0, baseline=0.15)
    scene = PlaneScene([(np.array([0.2, 0.1, 1.0]), 1.25, None),
                        (np.array([0, 0, 1.0]), 1.0, (-0.1, 0.05, -0.08, 0.05))])
    Wp, Hp = proj["size"]
    pats = opencv_patterns(Wp, Hp) + [np.full((Hp, Wp), 255, np.uint8), np.zeros((Hp, Wp), np.uint8)]
    rng = np.random.default_rng(0)
    out = []
    for cam in (cam0, cam1):
        imgs, z = render_projection(pats, proj, cam, scene, noise=0.005, rng=rng)
        dec = decode_graycode(imgs[:-2], imgs[-2], imgs[-1], 1.0, GrayCodeConfig(Wp, Hp))
        out.append((cam, dec, z))
    return out


def test_depth_from_codes_every_scale(plane_capture):
    (cam0, d0, z0), (cam1, d1, _z1) = plane_capture
    c0 = CameraCalibration(cam0["K"], cam0["dist"], cam0["size"])
    c1 = CameraCalibration(cam1["K"], cam1["dist"], cam1["size"])
    rays = normalised_rays(c0)
    # pixels of cam0 whose surface point cam1 sees inside its image (the plane scene has no occlusion in cam1
    # that matters for this check) and the projector lights (everything here)
    X = np.concatenate([rays, np.ones(rays.shape[:2] + (1,))], -1) * z0[..., None]
    X1 = X.reshape(-1, 3) @ cam1["R"].T + cam1["t"]
    uv = X1[:, :2] / X1[:, 2:] * cam1["K"][0, 0] + cam1["K"][:2, 2]
    both = ((uv[:, 0] > 3) & (uv[:, 0] < cam1["size"][0] - 4) & (uv[:, 1] > 3) & (uv[:, 1] < cam1["size"][1] - 4))
    both = both.reshape(z0.shape)
    depths = []
    for s in range(4):
        v0 = code_view(*d0.at_scale(s), d0.scale_size(s))
        v1 = code_view(*d1.at_scale(s), d1.scale_size(s))
        q, ok = match_in_other(v0, v1)
        depth = depth_from_match(rays, c0.K[0, 0], q, ok, c1, cam1["R"], cam1["t"])
        good = np.isfinite(depth)
        assert good[both].mean() > 0.85, (s, good[both].mean())
        rel = np.abs(depth[good] - z0[good]) / z0[good]
        assert np.median(rel) < 0.006, (s, np.median(rel))
        depths.append(depth)
    fused = recursive_fill(depths, 4)
    good = np.isfinite(fused)
    assert good[both].mean() > 0.95
    assert np.median(np.abs(fused[good] - z0[good]) / z0[good]) < 0.006  # ~0.25 px of a 48 px disparity


def test_close_holes_fills_small_holes_only():
    d = np.full((40, 40), 2.0, np.float32)
    d[10, 10] = np.nan  # small hole
    d[20:35, 20:35] = np.nan  # large hole
    out = close_holes(d, 3)
    assert out[10, 10] == pytest.approx(2.0)
    assert np.isnan(out[27, 27])


def test_statistical_outliers_match_reference_and_remove_planted():
    rng = np.random.default_rng(3)
    H, W = 60, 80
    xs, ys = np.meshgrid(np.linspace(-0.2, 0.2, W), np.linspace(-0.15, 0.15, H))
    rays = np.stack([xs, ys], -1).astype(np.float32)
    depth = (1.5 + 0.001 * rng.standard_normal((H, W))).astype(np.float32)
    spikes = rng.choice(H * W, 30, replace=False)
    depth.ravel()[spikes] += 0.5
    out = statistical_outliers(depth, rays, 20, 2.0)
    removed = np.isnan(out)
    assert removed.ravel()[spikes].all()
    # the same set as the documented Open3D semantics (self included, Bessel-corrected std)
    P = np.column_stack([rays[..., 0].ravel() * depth.ravel(), rays[..., 1].ravel() * depth.ravel(), depth.ravel()])
    dist, _ = cKDTree(P).query(P, k=20)
    avg = dist.mean(1)
    keep = (avg > 0) & (avg < avg[avg > 0].mean() + 2.0 * avg[avg > 0].std(ddof=1))
    np.testing.assert_array_equal(~removed.ravel(), keep)


@pytest.mark.parametrize("invalid_fraction", [0.3, 0.02, 0.0])
def test_valid_median_equals_nanmedian_reference(invalid_fraction):
    rng = np.random.default_rng(4)
    d = rng.uniform(1, 2, (30, 40)).astype(np.float32)
    d[rng.random((30, 40)) < invalid_fraction] = np.nan  # 0.02 and 0: mostly full windows (cv2.medianBlur path)
    out = valid_median(d, 5)
    pad = np.pad(d, 2, constant_values=np.nan)
    ref = np.full_like(d, np.nan)
    for y in range(30):  # reference loop on a tiny image (test only)
        for x in range(40):
            if np.isfinite(d[y, x]):
                ref[y, x] = np.nanmedian(pad[y:y + 5, x:x + 5])
    np.testing.assert_allclose(out, ref, rtol=1e-6)


def test_recursive_fill_eq3_order_and_steps():
    a = np.array([[1.0, np.nan, np.nan, np.nan]], np.float32)
    b = np.array([[9.0, 2.0, np.nan, np.nan]], np.float32)
    c = np.array([[9.0, 9.0, 3.0, np.nan]], np.float32)
    e = np.array([[9.0, 9.0, 9.0, 4.0]], np.float32)
    np.testing.assert_array_equal(recursive_fill([a, b, c, e], 3), [[1, 2, 3, np.nan]])
    np.testing.assert_array_equal(recursive_fill([a, b, c, e], 4), [[1, 2, 3, 4]])


def test_huber_skip_mean_clean_outliers_and_mad_zero():
    rng = np.random.default_rng(5)
    clean = 2000 + 5 * rng.standard_normal(600)
    # clean Gaussian data: normalised MAD with tau 3.5 keeps (almost) everything -> the plain mean
    assert huber_skip_mean(clean) == pytest.approx(clean.mean(), abs=0.05)
    dirty = clean.copy()
    dirty[:60] = 3500.0  # 10 % planted outliers (background through a hole)
    assert abs(huber_skip_mean(dirty) - 2000) < 1.0
    assert abs(dirty.mean() - 2000) > 100
    assert huber_skip_mean(np.r_[np.full(10, 1500.0), 1400.0, 1700.0]) == 1500.0  # MAD = 0 -> median
    raw = huber_skip_mean(clean, scaled_mad=False)
    assert raw != huber_skip_mean(clean)  # raw MAD drops ~2 % of clean samples


def test_focus_distance_window_and_errors():
    d = np.full((112, 168), 2500.0)
    d[:, :84] = 1200.0
    assert focus_distance(d, (120, 50)) == 2500.0
    assert focus_distance(d, (120, 50), FocusConfig(window_px=(60, 40))) == 2500.0
    with pytest.raises(BadInputError, match="outside"):
        focus_distance(d, (170, 50))
    d[30:70, 100:140] = 0
    with pytest.raises(StageError, match="no valid depth"):
        focus_distance(d, (120, 50))


def test_thin_focal_length_lens_or_eq7():
    from dp5k_process.pipeline import thin_focal_length

    assert thin_focal_length(85.0, 87.76, 2000.0) == (85.0, "lens")
    f, src = thin_focal_length(None, 87.76, 2700.0)  # the studio's pinhole f is the image distance at 2.7 m
    assert "Eq. 7" in src and f == pytest.approx(85.0, abs=0.01)


def test_valid_median_chunks_equal_whole():
    rng = np.random.default_rng(6)
    d = rng.uniform(1, 2, (70, 33)).astype(np.float32)
    d[rng.random((70, 33)) < 0.4] = np.nan
    np.testing.assert_array_equal(valid_median(d, 5, chunk_px=16), valid_median(d, 5, chunk_px=100000))


def test_fill_steps_follow_the_camera_resolution():
    """Eq. 3's 3 steps (scales 1, 1/2, 1/4) where a projector pixel spans >= 1 camera pixel; one coarser step
    per scale finer than a camera pixel (up to the 4 decoded scales)."""
    from dp5k_process.pipeline import fill_steps_for
    from dp5k_process.triangulate import camera_px_per_projector_px
    from dp5k_process.triangulate import code_view

    H, W = 60, 80
    ys, xs = np.mgrid[0:H, 0:W]
    valid = np.ones((H, W), bool)
    for per_px, steps in ((0.5, 3), (0.9, 3), (1.5, 4), (4.0, 4)):  # projector px per camera px
        col = np.floor(xs * per_px).astype(np.int32)
        row = np.floor(ys * per_px).astype(np.int32)
        v = code_view(col, row, valid, (int(W * per_px) + 1, int(H * per_px) + 1))
        assert camera_px_per_projector_px(v) == pytest.approx(1.0 / per_px, rel=0.05)
        assert fill_steps_for(v, 3, 4) == steps
    assert fill_steps_for(v, 3, 3) == 3


def test_midpoint_triangulate_known_point_gap_and_behind():
    """Rays from the origin and from the other camera (X_other = R X_ref + T) through a known point meet there with
    zero gap; moving the other ray 2 cm along y leaves a 2 cm gap and the midpoint between; a point behind is NaN."""
    R = cv2.Rodrigues(np.array([0.02, -0.1, 0.01]))[0]
    T = np.array([-0.3, 0.01, 0.02])
    X = np.array([[0.2, -0.1, 2.0], [-0.4, 0.3, 5.0]])
    Xo = X @ R.T + T
    pts, gap = midpoint_triangulate(X / X[:, 2:], Xo / Xo[:, 2:], R, T)
    np.testing.assert_allclose(pts, X, atol=1e-9)
    np.testing.assert_allclose(gap, 0.0, atol=1e-9)
    shifted = X + [0.0, 0.02, 0.0]  # the other camera sees a point 2 cm off, along a direction across both rays
    So = shifted @ R.T + T
    pts, gap = midpoint_triangulate(X / X[:, 2:], So / So[:, 2:], R, T)
    assert np.all(gap > 0.005) and np.all(gap <= 0.02 + 1e-9)
    behind = midpoint_triangulate(-X[:1] / X[:1, 2:], Xo[:1] / Xo[:1, 2:], R, T)[0]
    assert np.isnan(behind).all()


def test_midpoint_depth_equals_midpoint_triangulate():
    """The per-component depth path gives midpoint_triangulate's z and gap (skew rays, rays behind, 10^4 rays)."""
    rng = np.random.default_rng(3)
    R = cv2.Rodrigues(np.array([0.02, -0.1, 0.01]))[0]
    T = np.array([-0.3, 0.01, 0.02])
    n = 10_000
    a = np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), np.ones(n)])
    X = a * rng.uniform(-1.0, 6.0, (n, 1))  # a tenth behind the reference camera
    Xo = X @ R.T + T
    b = Xo / Xo[:, 2:] + np.column_stack([rng.normal(0, 2e-3, (n, 2)), np.zeros(n)])  # rays that miss
    pts, gap = midpoint_triangulate(a, b, R, T)
    z, gap2 = midpoint_depth(a[:, 0], a[:, 1], b[:, 0], b[:, 1], R, T)
    assert np.isnan(z).sum() > n // 20
    np.testing.assert_array_equal(np.isnan(z), np.isnan(pts[:, 2]))
    np.testing.assert_allclose(z, pts[:, 2], rtol=1e-12, atol=1e-12, equal_nan=True)
    np.testing.assert_allclose(gap2, gap, rtol=1e-9, atol=1e-12)


def test_undistort_px_equals_opencv_with_and_without_distortion():
    K = np.array([[3276.5, 0.0, 673.7], [0.0, 3270.0, 441.7], [0.0, 0.0, 1.0]])
    px = np.random.default_rng(4).uniform([0, 0], [1344, 896], (5000, 2))
    for dist in (np.zeros(5), np.array([-0.08, 0.05, 1e-3, -1e-3, 0.0])):
        cam = CameraCalibration(K, dist, (1344, 896))
        ref = cv2.undistortPoints(px.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
        np.testing.assert_allclose(undistort_px(px, cam), ref, rtol=0, atol=1e-12)


def _match_in_other_per_map(ref, other, cfg, coarse):
    """match_in_other as it was before the code maps were sampled together: one cv2.remap per map."""
    def remap(img, x, y):
        return cv2.remap(img, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    q, w = sample_centroids(coarse.centroids, coarse.from_full(ref.to_full(ref.u)), coarse.from_full(ref.to_full(ref.v)))
    ok = ref.valid & np.isfinite(ref.u) & np.isfinite(ref.v) & (w > 0) & np.isfinite(q[..., 0])
    valid_o = np.where(np.isfinite(other.u) & np.isfinite(other.v), 1.0, 0.0).astype(np.float32)
    uo, vo = np.nan_to_num(other.u), np.nan_to_num(other.v)
    step_max = 2.0 * max(1.0, other.footprint_px, coarse.footprint_px)
    for _ in range(cfg.newton_iters):
        qx = np.where(ok, q[..., 0], -10).astype(np.float32)
        qy = np.where(ok, q[..., 1], -10).astype(np.float32)
        m, cu, cv_, gr = (remap(x, qx, qy) for x in (valid_o, uo, vo, other.grads))
        du, dv = np.nan_to_num(ref.u) - cu, np.nan_to_num(ref.v) - cv_
        a, b, c, d = gr[..., 0], gr[..., 1], gr[..., 2], gr[..., 3]
        det = a * d - b * c
        with np.errstate(invalid="ignore", divide="ignore"):
            sx, sy = (d * du - b * dv) / det, (-c * du + a * dv) / det
        good = ok & (m > 0.999) & (np.abs(det) > 1e-8) & (np.abs(sx) <= step_max) & (np.abs(sy) <= step_max)
        q[..., 0] = np.where(good, q[..., 0] + sx, q[..., 0])
        q[..., 1] = np.where(good, q[..., 1] + sy, q[..., 1])
        ok = good
    qx = np.where(ok, q[..., 0], -10).astype(np.float32)
    qy = np.where(ok, q[..., 1], -10).astype(np.float32)
    res = np.hypot(np.nan_to_num(ref.u) - remap(uo, qx, qy), np.nan_to_num(ref.v) - remap(vo, qx, qy))
    ok &= (remap(valid_o, qx, qy) > 0.999) & (res <= cfg.max_code_residual)
    q[~ok] = np.nan
    return q, ok


def test_match_in_other_equals_one_remap_per_map(plane_capture):
    """Sampling the other camera's u, v and validity in one 3-channel remap gives the per-map result exactly."""
    (_c0, d0, _z0), (_c1, d1, _z1) = plane_capture
    cfg = TriangulationConfig()
    coarse = code_view(*d1.at_scale(3), d1.scale_size(3), cfg, 3)
    for s in (0, 2):
        v0 = code_view(*d0.at_scale(s), d0.scale_size(s), cfg, s)
        v1 = code_view(*d1.at_scale(s), d1.scale_size(s), cfg, s)
        q, ok = match_in_other(v0, v1, cfg, coarse=coarse)
        q_ref, ok_ref = _match_in_other_per_map(v0, v1, cfg, coarse)
        assert ok.mean() > 0.5
        np.testing.assert_array_equal(ok, ok_ref)
        np.testing.assert_array_equal(q, q_ref)
