"""Issue 22, third pass: the faster depth step gives what the code before it gave (``depth_before_pass3``, the
functions of commit a50fa0b kept verbatim), bit for bit."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.calibrate import CameraCalibration
from dp5k_process import triangulate
from dp5k_process.pipeline import ProcessConfig, projector_correspondences
from dp5k_process.projector import ProjectorCalibConfig
from dp5k_process.refine import cached_centroids, cached_view
from dp5k_process.filters import backproject
from dp5k_process.triangulate import (CentroidMap, CodeView, TriangulationConfig, centroid_map, code_view,
                                      depth_from_match, match_in_other, midpoint_depth)

from . import depth_before_pass3 as before
from .scene_steps import calibrated_and_decoded
from .test_depth_stages import plane_capture  # noqa: F401  (the module-scoped fixture)


def _assert_same_view(new: CodeView, old: CodeView) -> None:
    for name in ("u", "v", "valid", "centroids", "grads"):
        np.testing.assert_array_equal(getattr(new, name), getattr(old, name), err_msg=name)
    assert new.footprint_px == old.footprint_px and new.scale == old.scale


def test_code_view_and_centroid_map_equal_before(plane_capture):  # noqa: F811
    """One blurred mask for both codes, centroids from boolean indexing, a centroid map computed alone or reused:
    the same views as before."""
    cfg = TriangulationConfig()
    for _cam, dec, _z in plane_capture:
        for s in range(dec.cfg.n_scales):
            args = (*dec.at_scale(s), dec.scale_size(s))
            old = before.code_view(*args, cfg, s)
            _assert_same_view(code_view(*args, cfg, s), old)
            cm = centroid_map(*args, s)
            np.testing.assert_array_equal(cm.centroids, old.centroids)
            assert cm.footprint_px == old.footprint_px
            _assert_same_view(code_view(*args, cfg, s, centroids=cm), old)


def test_cached_centroids_then_view_equal_before(plane_capture):  # noqa: F811
    """The depth step's coarse view is a centroid map in the cache; a later full view of it reuses the map."""
    decs = {"cam0": plane_capture[0][1], "cam1": plane_capture[1][1]}
    cfg = TriangulationConfig()
    cache: dict = {}
    cm = cached_centroids(decs, "cam1", 3, cache)
    assert isinstance(cm, CentroidMap) and cached_centroids(decs, "cam1", 3, cache) is cm
    view = cached_view(decs, "cam1", 3, cfg, cache)
    _assert_same_view(view, before.code_view(*decs["cam1"].at_scale(3), decs["cam1"].scale_size(3), cfg, 3))
    assert cached_centroids(decs, "cam1", 3, cache) is view and ("cam1/centroids", 3) not in cache


@pytest.mark.parametrize("block_px", [triangulate.MATCH_BLOCK_PX, 1000, 1])
def test_blocked_match_in_other_equals_before(plane_capture, block_px):  # noqa: F811
    """Matching in blocks of rows (the last one partial), with the start from the other camera's own centroids,
    from a coarse code view or from a coarse centroid map: the same matches as the whole-image code."""
    (_c0, d0, _z0), (_c1, d1, _z1) = plane_capture
    cfg = TriangulationConfig()
    coarse = before.code_view(*d1.at_scale(3), d1.scale_size(3), cfg, 3)
    coarse_map = centroid_map(*d1.at_scale(3), d1.scale_size(3), 3)
    for s in (0, 2):
        v0 = before.code_view(*d0.at_scale(s), d0.scale_size(s), cfg, s)
        v1 = before.code_view(*d1.at_scale(s), d1.scale_size(s), cfg, s)
        for c_old, c_new in ((None, None), (coarse, coarse), (coarse, coarse_map)):
            q_ref, ok_ref = before.match_in_other(v0, v1, cfg, coarse=c_old)
            q, ok = match_in_other(v0, v1, cfg, coarse=c_new, block_px=block_px)
            assert ok_ref.mean() > 0.3
            np.testing.assert_array_equal(ok, ok_ref)
            np.testing.assert_array_equal(q, q_ref)


@pytest.mark.parametrize("chunk", [triangulate.TRIANGULATE_CHUNK, 777])
def test_chunked_triangulation_equals_before(plane_capture, monkeypatch, chunk):  # noqa: F811
    """Triangulating in chunks (with and without lens distortion in the other camera) changes no bit."""
    monkeypatch.setattr(triangulate, "TRIANGULATE_CHUNK", chunk)
    rng = np.random.default_rng(3)
    R = cv2.Rodrigues(np.array([0.02, -0.1, 0.01]))[0]
    T = np.array([-0.3, 0.01, 0.02])
    n = 10_000
    xa, ya, xb, yb = (rng.uniform(-0.3, 0.3, n) for _ in range(4))
    for new, old in zip(midpoint_depth(xa, ya, xb, yb, R, T), before.midpoint_depth(xa, ya, xb, yb, R, T)):
        np.testing.assert_array_equal(new, old)

    (cam0, d0, _z0), (cam1, d1, _z1) = plane_capture
    cfg = TriangulationConfig()
    v0, v1 = (before.code_view(*d.at_scale(0), d.scale_size(0), cfg, 0) for d in (d0, d1))
    q, ok = before.match_in_other(v0, v1, cfg)
    c0 = CameraCalibration(cam0["K"], np.zeros(5), cam0["size"])
    rays = triangulate.normalised_rays(c0)
    R, T = cam1["R"] @ cam0["R"].T, cam1["t"] - cam1["R"] @ cam0["R"].T @ cam0["t"]
    for dist in (np.zeros(5), np.array([-0.05, 0.01, 0.0, 0.0, 0.0])):
        c1 = CameraCalibration(cam1["K"], dist, cam1["size"])
        old = before.depth_from_match(rays, float(c0.K[0, 0]), q, ok, c1, R, T, cfg)
        new = depth_from_match(rays, float(c0.K[0, 0]), q, ok, c1, R, T, cfg)
        assert np.isfinite(old).mean() > 0.3
        np.testing.assert_array_equal(new, old)


def _projector_inputs_before(views, depths, rays, cfg: ProjectorCalibConfig):
    """What calibrate_projector fitted before: every scale's backprojected points and codes, the finite ones, then
    the seeded subset (the gathering of a50fa0b's depth_for_camera and the start of its calibrate_projector)."""
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
def test_projector_correspondences_equal_before(max_points):
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
    X_ref, x_ref = _projector_inputs_before(views, depths, rays, cfg)
    X, x = projector_correspondences(views, depths, rays, cfg)
    assert len(X_ref) == min(max_points, len(X_ref)) and len(X_ref) > 5
    np.testing.assert_array_equal(X, X_ref)
    np.testing.assert_array_equal(x, x_ref)


@pytest.mark.slow
def test_depth_for_camera_equals_before(tmp_path_factory):
    """The whole depth step of both cameras (shared views as ``process_scene`` shares them) equals a50fa0b's."""
    from dp5k_process.pipeline import depth_for_camera
    from dp5k_process.session import load_session
    from dp5k_testing.sim_session import write_session

    root = tmp_path_factory.mktemp("raw")
    write_session(root, "wall", f_numbers=(1.8,), board_on_wall=True)
    session = load_session(root / "wall")
    cfg = ProcessConfig()
    st, decs = calibrated_and_decoded(session, cfg)
    cache: dict = {}
    for cam in ("cam0", "cam1"):
        new, info = depth_for_camera(decs, cam, st, cfg, cache)
        old, info_old = before.depth_for_camera(decs, cam, st, cfg)
        assert np.isfinite(old).mean() > 0.5
        np.testing.assert_array_equal(new, old)
        assert info == info_old
