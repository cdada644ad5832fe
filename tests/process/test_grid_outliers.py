"""The grid outlier filter (``dp5k_process.grid_outliers``) against Open3D's ``remove_statistical_outlier``."""

from __future__ import annotations

import numpy as np
import pytest

import dp5k_process.grid_outliers as go
from dp5k_process.filters import FilterConfig, filter_depth, statistical_outliers

MAX_DIFFERING_FRACTION = 0.01
"""Valid pixels on which the grid filter and Open3D may decide differently (measured: 0.2-0.4 %)."""


def organised_scene(H: int = 120, W: int = 180, seed: int = 3):
    """A tilted plane at ~1.5 m with a 0.4 m step, a hole, 0.5 % spikes along the rays and a column of flying
    pixels half way across the step; returns (noisy depth, true depth, rays, spike mask, flying mask), metres;
    pixel footprint ~2 mm, noise 0.5 mm."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(-0.2, 0.2, W), np.linspace(-0.15, 0.15, H))
    rays = np.stack([xs, ys], -1).astype(np.float32)
    truth = (1.5 + 0.3 * xs).astype(np.float32)
    truth[:, W // 2:] += 0.4
    depth = truth + 0.0005 * rng.standard_normal((H, W)).astype(np.float32)
    spikes = np.zeros(H * W, bool)
    spikes[rng.choice(H * W, H * W // 200, replace=False)] = True
    spikes = spikes.reshape(H, W)
    depth[spikes] += rng.uniform(0.05, 0.3, spikes.sum()) * rng.choice([-1, 1], spikes.sum())
    spikes[:, W // 2] = False
    flying = np.zeros((H, W), bool)
    flying[:, W // 2] = True
    depth[flying] = truth[:, W // 2 - 1] + 0.2
    depth[40:52, 30:45] = np.nan
    return depth, truth, rays, spikes, flying


def test_grid_filter_agrees_with_open3d_and_removes_the_planted_outliers():
    depth, _, rays, spikes, flying = organised_scene()
    valid = np.isfinite(depth)
    o3d_removed = np.isnan(statistical_outliers(depth, rays, 20, 2.0)) & valid
    grid_removed = go.grid_outlier_mask(depth, rays, 20, 2.0, window_px=7)
    assert not (grid_removed & ~valid).any()
    assert (grid_removed != o3d_removed)[valid].mean() < MAX_DIFFERING_FRACTION
    assert grid_removed[spikes].mean() > 0.95 and o3d_removed[spikes].mean() > 0.95
    # a line of flying pixels is its own small "surface" to a KD-tree (Open3D keeps about half of it); on the
    # grid its 19 nearest include pixels of both real surfaces, so the grid filter removes it
    assert grid_removed[flying].mean() > 0.95
    assert grid_removed[valid & ~spikes & ~flying].mean() < 0.01  # the surfaces, their edges, the hole's rim stay


def test_grid_filter_chain_depth_error_and_coverage_not_worse_than_open3d():
    depth, truth, rays, _, _ = organised_scene(seed=5)
    out = {m: filter_depth(depth, rays, FilterConfig(sor_method=m)) for m in ("grid", "open3d")}
    err = {m: np.nanmedian(np.abs(d - truth) / truth) for m, d in out.items()}
    bad = {m: np.nanmean(np.abs(d - truth) / truth > 0.01) for m, d in out.items()}
    cov = {m: np.isfinite(d).mean() for m, d in out.items()}
    assert err["grid"] <= err["open3d"] * 1.05
    assert bad["grid"] <= bad["open3d"] + 0.001
    assert abs(cov["grid"] - cov["open3d"]) < 0.01


def test_the_bound_only_skips_pixels_the_exact_selection_keeps(monkeypatch):
    """Every pixel goes through the exact selection when the bound certifies none: the same mask."""
    depth, _, rays, _, _ = organised_scene(seed=7)
    fast = go.grid_outlier_mask(depth, rays)
    nan = np.full(depth.shape, np.nan, np.float32)
    monkeypatch.setattr(go, "bound_sum_m", lambda P, off: (nan, nan))
    np.testing.assert_array_equal(fast, go.grid_outlier_mask(depth, rays))


def test_bound_offsets_are_the_nearest_rings():
    half = go.bound_offsets(7, 19)
    assert len(half) == 10 and ((half ** 2).sum(1) <= 5).all()
    with pytest.raises(ValueError):
        go.grid_outlier_mask(np.ones((9, 9), np.float32), np.zeros((9, 9, 2), np.float32), 20, 2.0, window_px=4)


def test_on_a_noisy_plane_the_grid_statistic_is_the_kdtree_one():
    """Where the 19 nearest 3D neighbours lie in the window (a plane, noise below the pixel footprint), the grid
    filter computes Open3D's statistic (the documented KD-tree semantics): the same pixels fall above
    mean + 2 std (about 6 % of them, most on the image border)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(11)
    H, W = 90, 120
    xs, ys = np.meshgrid(np.linspace(-0.2, 0.2, W), np.linspace(-0.15, 0.15, H))
    rays = np.stack([xs, ys], -1).astype(np.float32)
    depth = (2.0 + 0.003 * rng.standard_normal((H, W))).astype(np.float32)  # footprint 6.7 mm
    P = np.column_stack([(rays[..., 0] * depth).ravel(), (rays[..., 1] * depth).ravel(), depth.ravel()])
    avg = cKDTree(P).query(P, k=20)[0].mean(1)
    ref = (avg >= avg.mean() + 2.0 * avg.std(ddof=1)).reshape(H, W)
    assert 0.01 < ref.mean() < 0.1  # the image border (fewer neighbours near) and the noisiest pixels
    np.testing.assert_array_equal(go.grid_outlier_mask(depth, rays), ref)
