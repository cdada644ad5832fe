"""DP image formation: energy (Eq. 2), mirror symmetry, CoC (Eq. 6), disparity sign/magnitude, occlusion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dp5k_studio import Studio, coc_channels_px, left_kernel, make_rig, plane_scene, render_dp
from dp5k_common.optics import coc_diameter_px

from .helpers import PITCH_MM, dot_views, lens, lowfreq_disparity_px, moments, textured


def test_coc_map_is_eq6_without_effects() -> None:
    depth = np.linspace(300.0, 9000.0, 60).reshape(6, 10)
    got = coc_channels_px(depth, lens(2.8, 2500.0))
    want = coc_diameter_px(depth, 2500.0, 85.0, 2.8, PITCH_MM)
    assert np.allclose(got, want[:, :, None], rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("c", [0.0, 0.4, 3.0, -7.5, 22.0])
def test_kernel_energy_and_half_disc_centroid(c: float) -> None:
    k = left_kernel(c)
    assert k.shape[0] == k.shape[1] and k.shape[0] % 2 == 1
    assert math.isclose(float(k.sum()), 1.0, rel_tol=1e-6)
    _, cx, cy, _, _ = moments(k)
    half = k.shape[0] // 2
    # left view: mass on the left half of the disc behind focus (c > 0), on the right half in front
    assert cx - half == pytest.approx(-2.0 * c / (3.0 * math.pi), abs=0.02 + 0.003 * abs(c))
    assert cy - half == pytest.approx(0.0, abs=1e-6)


def test_energy_left_plus_right_is_full_aperture_and_each_half_carries_half() -> None:
    H, W = 96, 128
    img = textured(H, W)
    depth = np.full((H, W), 3200.0)
    out = render_dp(img, depth, lens(1.8, 2000.0), full=True)
    assert np.allclose(out.left + out.right, out.full, atol=2e-5)
    inner = (slice(20, -20), slice(20, -20))
    for view in (out.left, out.right):
        assert view[inner].mean() == pytest.approx(0.5 * img[inner].mean(), rel=0.01)


def test_energy_with_occlusion_is_close() -> None:
    """At depth edges each half is composited with its own occlusion; the sum stays near the full render."""
    H, W = 96, 128
    img = textured(H, W, 1)
    depth = np.full((H, W), 4000.0)
    depth[30:70, 40:90] = 700.0
    out = render_dp(img, depth, lens(1.8, 2000.0), full=True)
    err = np.abs(out.left + out.right - out.full)
    assert err.mean() < 0.01 * out.full.mean()
    assert err.max() < 0.15


@pytest.mark.parametrize("depth_mm", [800.0, 4500.0])
def test_symmetry_right_psf_is_hflip_of_left(depth_mm: float) -> None:
    out = dot_views(depth_mm, lens(1.8, 2000.0))
    L = out.left[:, :, 1]
    R = out.right[:, :, 1]
    # the dot sits on the centre column: mirror about it
    assert np.allclose(R, L[:, ::-1], atol=1e-6 * L.max() + 1e-7)
    assert np.abs(R - L).max() > 0.05 * L.max()  # not trivially symmetric: the halves differ


@pytest.mark.parametrize("f_number,depth_mm", [(1.8, 4500.0), (2.8, 900.0), (5.6, 6000.0), (4.0, 1300.0)])
def test_coc_follows_eq6_for_a_fronto_parallel_plane(f_number: float, depth_mm: float) -> None:
    out = dot_views(depth_mm, lens(f_number, 2000.0), full=True, size=161)
    m, _, _, vx, vy = moments(out.full[:, :, 1])
    c = float(coc_diameter_px(depth_mm, 2000.0, 85.0, f_number, PITCH_MM))
    # a uniform disc of diameter c has var = c^2 / 16 per axis; + 1/6 px^2 from bilinear splatting
    diameter = 4.0 * math.sqrt(max(vx - 1.0 / 6.0, 0.0))
    assert m == pytest.approx(1.0, rel=1e-4)
    assert diameter == pytest.approx(abs(c), rel=0.04)
    assert vy == pytest.approx(vx, rel=0.05)


def test_coc_is_zero_at_the_focus_distance() -> None:
    out = dot_views(2000.0, lens(1.8, 2000.0), full=True)
    full = out.full[:, :, 1]
    assert full.max() > 0.99
    assert full[64, 64] == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("depth_mm", [900.0, 1500.0, 3000.0, 6000.0])
def test_dp_disparity_sign_and_magnitude_from_point_source(depth_mm: float) -> None:
    out = dot_views(depth_mm, lens(1.8, 2000.0), size=161)
    _, xl, _, _, _ = moments(out.left[:, :, 1])
    _, xr, _, _, _ = moments(out.right[:, :, 1])
    c = float(coc_diameter_px(depth_mm, 2000.0, 85.0, 1.8, PITCH_MM))
    disp = xr - xl
    assert math.copysign(1.0, disp) == math.copysign(1.0, c)  # behind focus: right view displaced to the right
    assert disp == pytest.approx(4.0 * c / (3.0 * math.pi), rel=0.03)


def test_dp_disparity_of_a_studio_plane() -> None:
    """A textured studio plane: cv2.phaseCorrelate(L, R) gives the documented sign (R right of L behind
    focus) and the low-frequency phase slope gives the documented magnitude 4c / (3 pi)."""
    import cv2

    rig = make_rig(20)
    for z_m, sign in ((4.0, 1.0), (1.2, -1.0)):
        st = Studio(plane_scene(z_m), rig, supersample=1)
        dp = st.render_views(0, 4.0, 2.0)
        L = np.ascontiguousarray(dp.left[:, :, 1]).astype(np.float64)
        R = np.ascontiguousarray(dp.right[:, :, 1]).astype(np.float64)
        (dx, _), _ = cv2.phaseCorrelate(L, R, cv2.createHanningWindow(L.shape[::-1], cv2.CV_64F))
        c = float(coc_diameter_px(z_m * 1000.0, 2000.0, 85.0, 4.0, rig.cameras[0].pixel_pitch_mm))
        assert math.copysign(1.0, dx) == sign
        assert lowfreq_disparity_px(L, R) == pytest.approx(4.0 * c / (3.0 * math.pi), rel=0.1)


def test_occlusion_foreground_spills_over_background_not_the_reverse() -> None:
    H, W = 80, 160
    img = np.full((H, W, 3), 0.1, np.float32)
    img[:, :80] = 0.9  # bright foreground on the left half
    depth = np.full((H, W), 5000.0)
    depth[:, :80] = 800.0
    row = slice(30, 50)
    # focus on the background: the blurred foreground spills over the sharp background
    a = render_dp(img, depth, lens(1.8, 5000.0), full=True).full
    c_fg = abs(float(coc_diameter_px(800.0, 5000.0, 85.0, 1.8, PITCH_MM)))
    assert a[row, 82:84].mean() > 0.1 + 0.1  # light beyond the edge
    assert a[row, 80 + int(c_fg / 2) + 2 :].mean() == pytest.approx(0.1, abs=1e-3)  # but not beyond the disc
    # focus on the foreground: the blurred background does not spill over the sharp foreground
    b = render_dp(img, depth, lens(1.8, 800.0), full=True).full
    assert np.allclose(b[row, :80], 0.9, atol=1e-3)
    # and the sharp foreground is not smeared into the background either
    assert np.allclose(b[row, 81:], 0.1, atol=2e-3)


def test_full_pipeline_views_add_up_in_a_studio_scene() -> None:
    rig = make_rig(20)
    st = Studio(plane_scene(3.0), rig, supersample=1)
    dp = st.render_views(1, 1.8, 2.0, full=True)  # toed-in camera: the plane spans several depth bins
    err = np.abs(dp.left + dp.right - dp.full)
    assert err.max() < 2e-3 and err.mean() < 2e-5


@pytest.mark.parametrize("coc_range", [(-1.0, -3.0), (1.0, 3.0), (-4.0, -5.7)])
def test_slanted_plane_matches_a_per_pixel_superposition(coc_range: tuple[float, float]) -> None:
    """A slanted plane (CoC varying along x, no occlusion) against the exact image of it: every pixel spreads
    its own half-disc PSF (coverage-normalised, as the renderer). With one CoC bin per pixel the blur was a
    staircase, 2-4e-3 rms off, as large as a planted PSF-shape effect; split between two bins it is < 6e-4."""
    H, W, P = 40, 96, 10
    yy, xx = np.mgrid[0:H, 0:W]
    img = np.where((xx // 6 + yy // 6) % 2 == 0, 0.8, 0.2).astype(np.float32)
    lz = lens(2.8, 2000.0)
    zs = np.geomspace(500.0, 50000.0, 200000)
    cz = coc_channels_px(zs[None, :], lz)[0, :, 1]  # increasing with depth
    depth = np.repeat(np.interp(np.linspace(*coc_range, W), cz, zs)[None, :], H, 0)
    out = render_dp(np.repeat(img[:, :, None], 3, 2), depth, lz)
    c = np.pad(out.coc_px[:, :, 1], P, mode="symmetric")
    src = np.pad(img, P, mode="symmetric")
    acc = np.zeros_like(src)
    cov = np.zeros_like(src)
    for x in range(src.shape[1]):  # the plane's CoC depends on x only: one kernel per column
        k = left_kernel(float(c[0, x]))
        h = k.shape[0] // 2
        if x - h < 0 or x + h >= src.shape[1]:
            continue
        for y in range(h, src.shape[0] - h):
            acc[y - h : y + h + 1, x - h : x + h + 1] += k * src[y, x]
            cov[y - h : y + h + 1, x - h : x + h + 1] += k
    truth = 0.5 * acc[P:-P, P:-P] / cov[P:-P, P:-P]
    err = (out.left[:, :, 1] - truth)[8:-8, 8:-8]
    assert float(np.sqrt(np.mean(err**2))) < 6e-4
