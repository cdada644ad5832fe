"""The fast paths of processing give what the reference implementations give (``tests/reference``), bit for bit:
Gray-code decoding, code views and matching, triangulation, the projector's correspondences, the grid outlier
filter and the DP views; and the whole depth step what its golden output holds (``tests/reference/make_golden.py``)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from calib.calibrate import CameraCalibration
from dp5k_common.rawfile import DualPixelFrames
from dp5k_process import grid_outliers, triangulate
from dp5k_process.filters import backproject
from dp5k_process.graycode import GrayCodeConfig, decode_graycode, opencv_patterns
from dp5k_process.grid_outliers import bound_offsets, bound_sum_m, grid_outlier_mask, organised_points
from dp5k_process.pipeline import _exposure_ratio, _unsaturated, projector_correspondences
from dp5k_process.projector import ProjectorCalibConfig
from dp5k_process.rawimage import dp_views, half_size_rgb
from dp5k_process.refine import cached_centroids, cached_view
from dp5k_process.triangulate import (CentroidMap, CodeView, TriangulationConfig, centroid_map, code_view,
                                      depth_from_match, match_in_other, midpoint_depth)
from dp5k_testing.procam_synth import PlaneScene, look_at_rig, render_projection

from ..reference import dp_views as dp_views_reference
from ..reference import graycode_decode, stereo_depth
from ..reference import grid_outliers as grid_outliers_reference
from ..reference.make_golden import DEPTH_FOR_CAMERA, depth_step_outputs
from .test_depth_stages import plane_capture  # noqa: F401  (the module-scoped fixture)


def _assert_same_view(new: CodeView, want: CodeView) -> None:
    for name in ("u", "v", "valid", "centroids", "grads"):
        np.testing.assert_array_equal(getattr(new, name), getattr(want, name), err_msg=name)
    assert new.footprint_px == want.footprint_px and new.scale == want.scale


def test_code_view_and_centroid_map_equal_reference(plane_capture):  # noqa: F811
    """One blurred mask for both codes, centroids from boolean indexing, a centroid map computed alone or reused:
    the same views as the reference."""
    cfg = TriangulationConfig()
    for _cam, dec, _z in plane_capture:
        for s in range(dec.cfg.n_scales):
            args = (*dec.at_scale(s), dec.scale_size(s))
            want = stereo_depth.code_view(*args, cfg, s)
            _assert_same_view(code_view(*args, cfg, s), want)
            cm = centroid_map(*args, s)
            np.testing.assert_array_equal(cm.centroids, want.centroids)
            assert cm.footprint_px == want.footprint_px
            _assert_same_view(code_view(*args, cfg, s, centroids=cm), want)


def test_cached_centroids_then_view_equal_reference(plane_capture):  # noqa: F811
    """The depth step's coarse view is a centroid map in the cache; a later full view of it reuses the map."""
    decs = {"cam0": plane_capture[0][1], "cam1": plane_capture[1][1]}
    cfg = TriangulationConfig()
    cache: dict = {}
    cm = cached_centroids(decs, "cam1", 3, cache)
    assert isinstance(cm, CentroidMap) and cached_centroids(decs, "cam1", 3, cache) is cm
    view = cached_view(decs, "cam1", 3, cfg, cache)
    _assert_same_view(view, stereo_depth.code_view(*decs["cam1"].at_scale(3), decs["cam1"].scale_size(3), cfg, 3))
    assert cached_centroids(decs, "cam1", 3, cache) is view and ("cam1/centroids", 3) not in cache


@pytest.mark.parametrize("block_px", [triangulate.MATCH_BLOCK_PX, 1000, 1])
def test_blocked_match_in_other_equals_reference(plane_capture, block_px):  # noqa: F811
    """Matching in blocks of rows (the last one partial), with the start from the other camera's own centroids,
    from a coarse code view or from a coarse centroid map: the same matches as the whole-image code."""
    (_c0, d0, _z0), (_c1, d1, _z1) = plane_capture
    cfg = TriangulationConfig()
    coarse = stereo_depth.code_view(*d1.at_scale(3), d1.scale_size(3), cfg, 3)
    coarse_map = centroid_map(*d1.at_scale(3), d1.scale_size(3), 3)
    for s in (0, 2):
        v0 = stereo_depth.code_view(*d0.at_scale(s), d0.scale_size(s), cfg, s)
        v1 = stereo_depth.code_view(*d1.at_scale(s), d1.scale_size(s), cfg, s)
        for c_ref, c_new in ((None, None), (coarse, coarse), (coarse, coarse_map)):
            q_ref, ok_ref = stereo_depth.match_in_other(v0, v1, cfg, coarse=c_ref)
            q, ok = match_in_other(v0, v1, cfg, coarse=c_new, block_px=block_px)
            assert ok_ref.mean() > 0.3
            np.testing.assert_array_equal(ok, ok_ref)
            np.testing.assert_array_equal(q, q_ref)


@pytest.mark.parametrize("chunk", [triangulate.TRIANGULATE_CHUNK, 777])
def test_chunked_triangulation_equals_reference(plane_capture, monkeypatch, chunk):  # noqa: F811
    """Triangulating in chunks (with and without lens distortion in the other camera) changes no bit."""
    monkeypatch.setattr(triangulate, "TRIANGULATE_CHUNK", chunk)
    rng = np.random.default_rng(3)
    R = cv2.Rodrigues(np.array([0.02, -0.1, 0.01]))[0]
    T = np.array([-0.3, 0.01, 0.02])
    n = 10_000
    xa, ya, xb, yb = (rng.uniform(-0.3, 0.3, n) for _ in range(4))
    for new, want in zip(midpoint_depth(xa, ya, xb, yb, R, T), stereo_depth.midpoint_depth(xa, ya, xb, yb, R, T)):
        np.testing.assert_array_equal(new, want)

    (cam0, d0, _z0), (cam1, d1, _z1) = plane_capture
    cfg = TriangulationConfig()
    v0, v1 = (stereo_depth.code_view(*d.at_scale(0), d.scale_size(0), cfg, 0) for d in (d0, d1))
    q, ok = stereo_depth.match_in_other(v0, v1, cfg)
    c0 = CameraCalibration(cam0["K"], np.zeros(5), cam0["size"])
    rays = triangulate.normalised_rays(c0)
    R, T = cam1["R"] @ cam0["R"].T, cam1["t"] - cam1["R"] @ cam0["R"].T @ cam0["t"]
    for dist in (np.zeros(5), np.array([-0.05, 0.01, 0.0, 0.0, 0.0])):
        c1 = CameraCalibration(cam1["K"], dist, cam1["size"])
        want = stereo_depth.depth_from_match(rays, float(c0.K[0, 0]), q, ok, c1, R, T, cfg)
        new = depth_from_match(rays, float(c0.K[0, 0]), q, ok, c1, R, T, cfg)
        assert np.isfinite(want).mean() > 0.3
        np.testing.assert_array_equal(new, want)


def _projector_inputs_reference(views, depths, rays, cfg: ProjectorCalibConfig):
    """The projector's correspondences, the straightforward way: every scale's backprojected points and codes, the
    finite ones, then the seeded subset drawn from all of them."""
    pts, codes = [], []
    for v, d in zip(views, depths):
        X, m = backproject(d, rays)
        pts.append(X)
        codes.append(np.column_stack([v.to_full(v.u)[m], v.to_full(v.v)[m]]))
    points_m, proj_px = np.concatenate(pts), np.concatenate(codes)
    ok = np.isfinite(points_m).all(1) & np.isfinite(proj_px).all(1)
    X, x = points_m[ok].astype(np.float64), proj_px[ok].astype(np.float64)
    if len(X) > cfg.max_points:
        idx = np.random.default_rng(cfg.seed).choice(len(X), cfg.max_points, replace=False)
        X, x = X[idx], x[idx]
    return X, x


@pytest.mark.parametrize("max_points", [20000, 3000, 10])
def test_projector_correspondences_equal_reference(max_points):
    """The projector's correspondences drawn from their count alone: the same points, codes and order as
    gathering all of them and drawing then (holes in depth and in codes, three scales, subset or not)."""
    rng = np.random.default_rng(5)
    H, W = 60, 80
    rays = np.stack(np.meshgrid((np.arange(W) - 40) / 500.0, (np.arange(H) - 30) / 500.0), -1).astype(np.float32)
    views, depths = [], []
    for s in range(3):
        u = rng.uniform(0, 1920 >> s, (H, W)).astype(np.float32)
        v = rng.uniform(0, 1200 >> s, (H, W)).astype(np.float32)
        u[rng.random((H, W)) < 0.1] = np.nan
        v[rng.random((H, W)) < 0.1] = np.nan
        d = rng.uniform(1.0, 3.0, (H, W)).astype(np.float32)
        d[rng.random((H, W)) < 0.2] = np.nan
        views.append(CodeView(u, v, np.isfinite(u), np.zeros((1, 1, 2), np.float32), np.zeros((H, W, 4), np.float32),
                              1.0, s))
        depths.append(d)
    cfg = ProjectorCalibConfig(max_points=max_points)
    X_ref, x_ref = _projector_inputs_reference(views, depths, rays, cfg)
    X, x = projector_correspondences(views, depths, rays, cfg)
    assert len(X_ref) == min(max_points, len(X_ref)) and len(X_ref) > 5
    np.testing.assert_array_equal(X, X_ref)
    np.testing.assert_array_equal(x, x_ref)


@pytest.fixture(scope="module")
def rendered_set():
    """A two-plane scene's Gray-code set (44 patterns, white, black) as float images in [0, 1]."""
    cam0, _cam1, proj = look_at_rig(f_px=400.0, baseline=0.15)
    scene = PlaneScene([(np.array([0.2, 0.1, 1.0]), 1.25, None),
                        (np.array([0, 0, 1.0]), 1.0, (-0.1, 0.05, -0.08, 0.05))])
    Wp, Hp = proj["size"]
    pats = opencv_patterns(Wp, Hp) + [np.full((Hp, Wp), 255, np.uint8), np.zeros((Hp, Wp), np.uint8)]
    imgs, _z = render_projection(pats, proj, cam0, scene, noise=0.02, rng=np.random.default_rng(1), ambient=0.05,
                                 gain=0.3, blur_sigma=1.2)
    return imgs, (Wp, Hp)


def _assert_same_decode(new, want) -> None:
    for name in ("col", "row", "col_bits", "row_bits", "lit"):
        a, b = getattr(new, name), getattr(want, name)
        assert a.dtype == b.dtype, name
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_decode_graycode_equals_reference(rendered_set):
    """In-place bit tests, the code built in uint16 and raw counts subtracted in float32 without float copies:
    the same decode for 14-bit raw counts (the package's loader hands uint16, the reference's float32), 8-bit and float images,
    with and without the neighbourhood levels."""
    imgs, (Wp, Hp) = rendered_set
    raw = [np.clip(np.rint(512 + im * 15871), 0, 16383).astype(np.uint16) for im in imgs]
    cfg_raw = GrayCodeConfig.for_linear_raw(Wp, Hp)
    want = graycode_decode.decode_graycode(lambda i: raw[i].astype(np.float32), raw[-2].astype(np.float32),
                                 raw[-1].astype(np.float32), 15871.0, cfg_raw)
    assert want.lit.mean() > 0.5 and (want.col_bits > 0).mean() > 0.5
    _assert_same_decode(decode_graycode(lambda i: raw[i], raw[-2].astype(np.float32), raw[-1].astype(np.float32),
                                        15871.0, cfg_raw), want)
    u8 = [np.clip(im * 255, 0, 255).astype(np.uint8) for im in imgs]
    for cfg in (GrayCodeConfig(Wp, Hp), GrayCodeConfig(Wp, Hp, max_weak_bits=0),
                GrayCodeConfig(Wp, Hp, denoise_px=3, denoise_line_px=7, agree_px=False)):
        _assert_same_decode(decode_graycode(u8[:-2], u8[-2], u8[-1], 255.0, cfg),
                            graycode_decode.decode_graycode(u8[:-2], u8[-2], u8[-1], 255.0, cfg))
        f64 = [im.astype(np.float64) for im in imgs]
        _assert_same_decode(decode_graycode(f64[:-2], f64[-2], f64[-1], 1.0, cfg),
                            graycode_decode.decode_graycode(f64[:-2], f64[-2], f64[-1], 1.0, cfg))


@pytest.mark.parametrize("block_px", [grid_outliers.BOUND_BLOCK_PX, 1000, 1])
def test_grid_outlier_filter_equals_reference(block_px, monkeypatch):
    """The bound pass in row blocks (blocks of many rows, a few rows, one row) and one padded copy for both
    exact selections: the same sums, maxima and removed pixels."""
    rng = np.random.default_rng(0)
    H, W = 150, 211
    xs, ys = np.meshgrid(np.linspace(-0.2, 0.2, W, dtype=np.float32), np.linspace(-0.15, 0.15, H, dtype=np.float32))
    rays = np.stack([xs, ys], -1)
    depth = (1.5 + 0.3 * xs + 0.0005 * rng.standard_normal((H, W), dtype=np.float32)).astype(np.float32)
    depth[:, W // 2:] += 0.4
    spikes = rng.random((H, W)) < 0.01
    depth[spikes] += rng.uniform(-0.3, 0.3, int(spikes.sum())).astype(np.float32)
    depth[40:70, 30:60] = np.nan
    depth[rng.random((H, W)) < 0.02] = np.nan
    P = organised_points(depth, rays)
    off = bound_offsets(7, 19)
    S0, M0 = grid_outliers_reference.bound_sum_m(P, off)
    S1, M1 = bound_sum_m(P, off, block_px)
    np.testing.assert_array_equal(S1, S0)
    np.testing.assert_array_equal(M1, M0)
    monkeypatch.setattr(grid_outliers, "BOUND_BLOCK_PX", block_px)
    monkeypatch.setattr(grid_outliers.bound_sum_m, "__defaults__", (block_px,))
    want = grid_outliers_reference.grid_outlier_mask(depth, rays)
    assert want.sum() > 0
    np.testing.assert_array_equal(grid_outlier_mask(depth, rays), want)


def test_dp_views_and_exposure_ratio_equal_reference():
    """Half-size RGB planes converted one by one and written in place, white balance in place, the unsaturated
    test by element-wise maxima and the sharp frame's computed once: the same views and ratio."""
    rng = np.random.default_rng(0)
    H, W = 64, 90
    main = rng.integers(400, 16383, (H, W)).astype(np.uint16)
    aux = (main // 2 + rng.integers(0, 300, (H, W))).astype(np.uint16)
    for cfa in ("RGGB", "BGGR", "GRBG"):
        fr = DualPixelFrames(main=main, aux=aux, black_level=512, white_level=16383, wb_gains=(1.9, 1.0, 1.4),
                             cfa_pattern=cfa)
        for aux_view in ("left", "right"):
            for a, b in zip(dp_views(fr, aux_view), dp_views_reference.dp_views(fr, aux_view)):
                assert a.dtype == b.dtype
                np.testing.assert_array_equal(a, b)
        odd = main[:-1, :-3].astype(np.float64) / 7
        np.testing.assert_array_equal(half_size_rgb(odd, 3.5, cfa), dp_views_reference.half_size_rgb(odd, 3.5, cfa))
    dp = rng.uniform(0, 1.05, (H, W, 3)).astype(np.float32)
    sharp = rng.uniform(0, 1.0, (H, W, 3)).astype(np.float32)
    sharp[3, 4, 1] = np.nan
    for s in (sharp, sharp * 0.5, sharp * 1.5):  # some, none and most pixels saturated
        np.testing.assert_array_equal(_unsaturated(s), dp_views_reference.unsaturated(s))
        np.testing.assert_equal(_exposure_ratio(dp, s), dp_views_reference.exposure_ratio(dp, s))  # NaN == NaN here
        np.testing.assert_equal(_exposure_ratio(dp, s, _unsaturated(s)), dp_views_reference.exposure_ratio(dp, s))


@pytest.mark.slow
def test_depth_for_camera_equals_its_golden_output(tmp_path_factory):
    """The whole depth step of both cameras (shared views as ``process_scene`` shares them) gives the golden
    depths and summaries (regenerate with ``tests/reference/make_golden.py`` only when a change is meant)."""
    golden = np.load(DEPTH_FOR_CAMERA)
    for cam, (depth, info) in depth_step_outputs(tmp_path_factory.mktemp("raw")).items():
        want = golden[f"{cam}_depth"]
        assert np.isfinite(want).mean() > 0.5
        np.testing.assert_array_equal(depth, want)
        assert json.loads(json.dumps(info, sort_keys=True)) == json.loads(str(golden[f"{cam}_info"]))
