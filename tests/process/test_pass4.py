"""Issue 22, fourth pass: the faster decode, views, code views and outlier filter give what the code before them
gave (``before_pass4``, the functions of commit ca9098a kept verbatim), bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from dp5k_common.rawfile import DualPixelFrames
from dp5k_process import grid_outliers
from dp5k_process.graycode import GrayCodeConfig, decode_graycode, opencv_patterns
from dp5k_process.grid_outliers import bound_offsets, bound_sum_m, grid_outlier_mask, organised_points
from dp5k_process.pipeline import _exposure_ratio, _unsaturated
from dp5k_process.rawimage import dp_views, half_size_rgb
from dp5k_process.triangulate import TriangulationConfig, code_view
from dp5k_testing.procam_synth import PlaneScene, look_at_rig, render_projection

from . import before_pass4 as before
from .test_depth_stages import plane_capture  # noqa: F401  (the module-scoped fixture)


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


def _assert_same_decode(new, old) -> None:
    for name in ("col", "row", "col_bits", "row_bits", "lit"):
        a, b = getattr(new, name), getattr(old, name)
        assert a.dtype == b.dtype, name
        np.testing.assert_array_equal(a, b, err_msg=name)


def test_decode_graycode_equals_before(rendered_set):
    """In-place bit tests, the code built in uint16 and raw counts subtracted in float32 without float copies:
    the same decode for 14-bit raw counts (the loader now hands uint16; before, float32), 8-bit and float images,
    with and without the neighbourhood levels."""
    imgs, (Wp, Hp) = rendered_set
    raw = [np.clip(np.rint(512 + im * 15871), 0, 16383).astype(np.uint16) for im in imgs]
    cfg_raw = GrayCodeConfig.for_linear_raw(Wp, Hp)
    old = before.decode_graycode(lambda i: raw[i].astype(np.float32), raw[-2].astype(np.float32),
                                 raw[-1].astype(np.float32), 15871.0, cfg_raw)
    assert old.lit.mean() > 0.5 and (old.col_bits > 0).mean() > 0.5
    _assert_same_decode(decode_graycode(lambda i: raw[i], raw[-2].astype(np.float32), raw[-1].astype(np.float32),
                                        15871.0, cfg_raw), old)
    u8 = [np.clip(im * 255, 0, 255).astype(np.uint8) for im in imgs]
    for cfg in (GrayCodeConfig(Wp, Hp), GrayCodeConfig(Wp, Hp, max_weak_bits=0),
                GrayCodeConfig(Wp, Hp, denoise_px=3, denoise_line_px=7, agree_px=False)):
        _assert_same_decode(decode_graycode(u8[:-2], u8[-2], u8[-1], 255.0, cfg),
                            before.decode_graycode(u8[:-2], u8[-2], u8[-1], 255.0, cfg))
        f64 = [im.astype(np.float64) for im in imgs]
        _assert_same_decode(decode_graycode(f64[:-2], f64[-2], f64[-1], 1.0, cfg),
                            before.decode_graycode(f64[:-2], f64[-2], f64[-1], 1.0, cfg))


def test_code_view_equals_before(plane_capture):  # noqa: F811
    """The gradients written in place instead of stacked: the same views."""
    cfg = TriangulationConfig()
    for _cam, dec, _z in plane_capture:
        for s in range(dec.cfg.n_scales):
            args = (*dec.at_scale(s), dec.scale_size(s))
            new, old = code_view(*args, cfg, s), before.code_view(*args, cfg, s)
            for name in ("u", "v", "valid", "centroids", "grads"):
                np.testing.assert_array_equal(getattr(new, name), getattr(old, name), err_msg=name)


@pytest.mark.parametrize("block_px", [grid_outliers.BOUND_BLOCK_PX, 1000, 1])
def test_grid_outlier_filter_equals_before(block_px, monkeypatch):
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
    S0, M0 = before.bound_sum_m(P, off)
    S1, M1 = bound_sum_m(P, off, block_px)
    np.testing.assert_array_equal(S1, S0)
    np.testing.assert_array_equal(M1, M0)
    monkeypatch.setattr(grid_outliers, "BOUND_BLOCK_PX", block_px)
    monkeypatch.setattr(grid_outliers.bound_sum_m, "__defaults__", (block_px,))
    old = before.grid_outlier_mask(depth, rays)
    assert old.sum() > 0
    np.testing.assert_array_equal(grid_outlier_mask(depth, rays), old)


def test_dp_views_and_exposure_ratio_equal_before():
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
            for a, b in zip(dp_views(fr, aux_view), before.dp_views(fr, aux_view)):
                assert a.dtype == b.dtype
                np.testing.assert_array_equal(a, b)
        odd = main[:-1, :-3].astype(np.float64) / 7
        np.testing.assert_array_equal(half_size_rgb(odd, 3.5, cfa), before.half_size_rgb(odd, 3.5, cfa))
    dp = rng.uniform(0, 1.05, (H, W, 3)).astype(np.float32)
    sharp = rng.uniform(0, 1.0, (H, W, 3)).astype(np.float32)
    sharp[3, 4, 1] = np.nan
    for s in (sharp, sharp * 0.5, sharp * 1.5):  # some, none and most pixels saturated
        np.testing.assert_array_equal(_unsaturated(s), before_unsaturated(s))
        np.testing.assert_equal(_exposure_ratio(dp, s), before._exposure_ratio(dp, s))  # NaN == NaN here
        np.testing.assert_equal(_exposure_ratio(dp, s, _unsaturated(s)), before._exposure_ratio(dp, s))


def before_unsaturated(img):
    return img.max(-1) < 0.98
