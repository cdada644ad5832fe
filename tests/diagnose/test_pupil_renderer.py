"""The third independent DP renderer (dp5k_testing/pupil_dp.py): pupil-function PSFs and layered occlusion.

Checked against the thin lens and Eq. 2, not against dp5k: clean views are the textured plane convolved with half
discs built here by supersampled area coverage, the left view lies left of the right one behind focus, each planted
effect changes what its physics says and nothing else that can be checked, a near layer hides what lies behind it,
the noise follows its stated model, and the writer's output is format v1. (It is held out from diagnose's tuning:
nothing here runs diagnose.)
"""

from __future__ import annotations

import ast
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dp5k_common.dataset import DatasetReader
from dp5k_common.effects import EFFECT_NAMES
from dp5k_testing import pupil_dp as pu
from dp5k_testing.pupil_scene import Layer, LayerScene, pink_noise, plane_scene, points_scene

SIZE = (96, 64)
PAD = 24
PITCH = 36.0 / 256  # the 256 px frame's pitch (mm)
LENS = pu.Lens(85.0, 2.0, 1200.0, PITCH)
NONE = pu.Effects.of("none")


def texture(seed: int = 0, size: tuple[int, int] = SIZE, pad: int = PAD) -> np.ndarray:
    W, H = size
    f = pink_noise(np.random.default_rng(seed), H + 2 * pad, W + 2 * pad, 1.0, 3)
    return (0.1 + 0.8 * np.stack(f, -1)).astype(np.float32)


def half_disc(c: float, side: int, ss: int = 48) -> np.ndarray:
    """Reference kernel, built independently: each pixel's area share (ss x ss samples) of the half of a disc of
    diameter |c| that ``side`` (+1 left, -1 right) receives (the left half for c > 0, the right half for c < 0),
    normalised so that the whole disc sums to 1."""
    if c == 0:
        return np.array([[0.5]])
    r = abs(c) / 2
    R = int(math.ceil(r)) + 1
    o = (np.arange(ss) + 0.5) / ss - 0.5
    g = np.arange(-R, R + 1)
    X = g[None, :, None, None] + o[None, None, None, :]
    Y = g[:, None, None, None] + o[None, None, :, None]
    inside = X**2 + Y**2 <= r * r
    half = inside & ((X < 0) if side * c > 0 else (X > 0))
    return half.sum((2, 3)) / inside.sum()


def convolve(img: np.ndarray, k: np.ndarray) -> np.ndarray:
    return cv2.filter2D(img, cv2.CV_32F, np.ascontiguousarray(k[::-1, ::-1]).astype(np.float32),
                        borderType=cv2.BORDER_CONSTANT)


def frame(img: np.ndarray, size: tuple[int, int] = SIZE, pad: int = PAD) -> np.ndarray:
    W, H = size
    return img[pad : pad + H, pad : pad + W]


def plane(c: float, lens: pu.Lens = LENS, seed: int = 0) -> tuple[LayerScene, np.ndarray]:
    tex = texture(seed)
    return plane_scene(SIZE, PAD, tex, lens.inv_depth_for_coc(c)), tex


def moments(img: np.ndarray, x: int, y: int, r: int = 14, ch: int = 1) -> tuple[float, float, float, float, float]:
    """(sum, centroid x, centroid y, variance x, variance y) of channel ``ch`` in a window around (x, y)."""
    w = img[y - r : y + r + 1, x - r : x + r + 1, ch].astype(np.float64)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    s = w.sum()
    cx, cy = (w * xx).sum() / s, (w * yy).sum() / s
    return s, cx, cy, (w * (xx - cx) ** 2).sum() / s, (w * (yy - cy) ** 2).sum() / s


POINTS_SIZE = (128, 86)
POINTS = [(64, 43), (16, 43), (112, 43), (64, 15)]  # centre, left and right side edges, top edge (frame px)


def point_views(c: float, effects: str | list[str] = "none", N: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Views of point sources on a plane whose Eq. 6 CoC is ``c`` (px) at f/``N`` (recorded focus 1 m)."""
    lens = pu.Lens(85.0, N, 1000.0, PITCH)
    scene = points_scene(POINTS_SIZE, 30, POINTS, lens.inv_depth_for_coc(c))
    return pu.render_views(scene, lens, pu.Effects.of(effects))


# ------------------------------------------------------------------------------------------------ clean = Eq. 2
@pytest.mark.parametrize("c", [-11.3, -4.0, -0.6, 0.0, 1.7, 6.2, 14.5])
def test_clean_views_are_the_plane_convolved_with_ideal_half_discs(c: float) -> None:
    scene, tex = plane(c)
    left, right = pu.render_views(scene, LENS, NONE)
    ref_l = frame(convolve(tex, half_disc(c, +1)))
    ref_r = frame(convolve(tex, half_disc(c, -1)))
    assert np.abs(left - ref_l).max() < 1e-3  # intensities ~0.25: the pupil sampling is ~1e-3 of the kernel peak
    assert np.abs(right - ref_r).max() < 1e-3
    full = half_disc(c, +1) + half_disc(c, -1)
    assert np.abs(left + right - frame(convolve(tex, full))).max() < 1.5e-3  # L + R is the full disc's blur


@pytest.mark.parametrize("c", [-9.0, -3.0, 4.0, 12.0])
def test_clean_kernels_are_mirror_half_discs_of_half_the_light(c: float) -> None:
    K_l, K_r = pu.psf(c, pu.LEFT, pu.Optics()), pu.psf(c, pu.RIGHT, pu.Optics())
    assert float(K_l.sum()) == pytest.approx(0.5, abs=1e-6) and float(K_r.sum()) == pytest.approx(0.5, abs=1e-6)
    assert np.abs(K_r - K_l[:, ::-1]).max() < 1e-6  # Eq. 2: the right PSF is the horizontal flip of the left
    ref = half_disc(c, +1)
    n = max(ref.shape[0], K_l.shape[0])
    pad = lambda k: np.pad(k, (n - k.shape[0]) // 2)  # noqa: E731
    assert np.abs(pad(K_l) - pad(ref)).max() < 2e-3 * ref.max() + 1e-6


@pytest.mark.parametrize("c", [-10.0, -4.0, 5.0, 16.0])
def test_left_view_lies_left_behind_focus_and_the_centroids_part_by_4c_over_3pi(c: float) -> None:
    left, right = point_views(c)
    x, y = POINTS[0]
    _, cxl, _, _, _ = moments(left, x, y)
    _, cxr, _, _, _ = moments(right, x, y)
    k_l, k_r = half_disc(c, +1), half_disc(c, -1)
    xs = np.arange(k_l.shape[1]) - k_l.shape[1] // 2
    sep_ref = (k_r.sum(0) * xs).sum() / k_r.sum() - (k_l.sum(0) * xs).sum() / k_l.sum()
    assert np.sign(cxr - cxl) == np.sign(c)  # behind focus R is displaced to the right of L (docs/conventions.md)
    assert cxr - cxl == pytest.approx(sep_ref, rel=0.01)
    assert abs(cxr - cxl) == pytest.approx(4 * abs(c) / (3 * math.pi), rel=0.03)  # pixel binning aside


@pytest.mark.parametrize("c", [-7.0, 7.0])
def test_phase_correlation_finds_the_right_view_shifted_the_way_of_the_sign(c: float) -> None:
    scene, _ = plane(c, seed=3)
    left, right = pu.render_views(scene, LENS, NONE)
    (dx, dy), _ = cv2.phaseCorrelate(left.mean(-1).astype(np.float64), right.mean(-1).astype(np.float64))
    assert np.sign(dx) == np.sign(c) and abs(dx) > 0.25 * abs(c) and abs(dy) < 0.3


def test_sharp_is_the_full_pupil_at_f22_or_the_radiance() -> None:
    scene, tex = plane(9.0)
    s22 = pu.render_sharp(scene, LENS, NONE, 22.0)
    c22 = 9.0 * LENS.f_number / 22.0
    assert np.abs(s22 - frame(convolve(tex, half_disc(c22, 1) + half_disc(c22, -1)))).max() < 1e-3
    assert np.array_equal(pu.render_sharp(scene, LENS, NONE, 0.0), frame(tex))


# ------------------------------------------------------------------------------------------------ effects
def test_every_effect_name_has_a_default_and_any_set_combines() -> None:
    assert set(pu.EFFECT_DEFAULTS) == set(EFFECT_NAMES)
    scene, _ = plane(6.0)
    left, right = pu.render_views(scene, LENS, pu.Effects.of(list(EFFECT_NAMES)))
    assert np.isfinite(left).all() and np.isfinite(right).all() and 0.1 < left.mean() < 0.4
    assert pu.Effects.of("noise+psf_profile", 2.0).a == {"noise": 2 * pu.EFFECT_DEFAULTS["noise"],
                                                        "psf_profile": 2 * pu.EFFECT_DEFAULTS["psf_profile"]}
    assert pu.Effects.of({"noise": 0.5}).a == {"noise": 0.5 * pu.EFFECT_DEFAULTS["noise"]}
    with pytest.raises(ValueError, match="unknown effect"):
        pu.Effects.of("vignetting")


def test_lr_gain_imbalance_scales_brightness_only_by_a_smooth_non_linear_field() -> None:
    scene, _ = plane(7.0)
    l0, r0 = pu.render_views(scene, LENS, NONE)
    l1, r1 = pu.render_views(scene, LENS, pu.Effects.of("lr_gain_imbalance"))
    gl, gr = pu.lr_gains(pu.Effects.of("lr_gain_imbalance"), SIZE)
    assert np.allclose(l1, l0 * gl[..., None], atol=1e-6) and np.allclose(r1, r0 * gr[..., None], atol=1e-6)
    assert np.allclose(gl + gr, 2.0)  # the photodiodes' light is moved between them, not lost
    ratio = gl / gr
    H, W = ratio.shape
    assert ratio[H // 2, -1] > 1.12 and ratio[H // 2, 0] < 0.97  # brighter left view toward the right edge
    assert ratio[0, W // 2] > ratio[H // 2, W // 2] + 0.015  # not linear: grows toward the top and bottom
    assert ratio[H // 2, W // 2] == pytest.approx(1.024, abs=0.005)


def test_field_varying_psf_makes_off_axis_ellipses_at_equal_coc_and_keeps_brightness() -> None:
    for c in (8.0, -8.0):
        left, right = point_views(c, "field_varying_psf")
        full = left + right
        s0, _, _, vx0, vy0 = moments(full, *POINTS[0])
        assert vx0 == pytest.approx(vy0, rel=0.01)  # on axis: a disc
        for x, y in POINTS[1:3]:  # the side edges: long along the field radius (x) behind focus, across in front
            s, _, _, vx, vy = moments(full, x, y)
            assert s == pytest.approx(s0, abs=1e-5)
            assert (vx / vy > 1.4) if c > 0 else (vy / vx > 1.4)
        s, _, _, vx, vy = moments(full, *POINTS[3])  # the top edge: radius along y
        assert (vy / vx > 1.1) if c > 0 else (vx / vy > 1.1)
        for x, y in POINTS:
            assert moments(left, x, y)[0] == pytest.approx(0.5, abs=1e-5)


def test_chromatic_defocus_focuses_red_and_blue_elsewhere_than_green() -> None:
    lens = pu.Lens(85.0, 2.0, 1000.0, PITCH)
    a = pu.EFFECT_DEFAULTS["chromatic_defocus"]
    vs = lens.sensor_distance_mm()
    inv = lens.inv_depth_for_coc(np.array([-8.0, 8.0]))
    for ch, dv in ((0, 0.55 * a), (2, a)):
        want = lens.channel_coc_px(inv, 0.0, dv) - lens.coc_px(1.0 / inv)  # about -A dv / v
        assert want == pytest.approx(-lens.aperture_mm * dv / vs / PITCH, rel=0.1)  # v varies with depth
    sizes = {}
    for c in (8.0, -8.0):
        left, right = point_views(c, "chromatic_defocus")
        sizes[c] = [moments(left + right, *POINTS[0], ch=k)[3] for k in range(3)]
    # both R and B image farther from the lens than G: behind focus their discs are smaller, in front larger
    assert sizes[8.0][2] < sizes[8.0][0] < sizes[8.0][1]
    assert sizes[-8.0][2] > sizes[-8.0][0] > sizes[-8.0][1]
    clean = point_views(8.0)
    assert np.array_equal(clean[0][..., 1], point_views(8.0, "chromatic_defocus")[0][..., 1])  # green is the lens


@pytest.mark.parametrize("N, ratio", [(2.0, 0.896), (4.0, 0.66)])
def test_disparity_scale_shrinks_the_lr_separation_and_keeps_left_plus_right(N: float, ratio: float) -> None:
    c = 16.0 / N
    l0, r0 = point_views(c, "none", N)
    l1, r1 = point_views(c, "disparity_scale", N)
    x, y = POINTS[0]
    sep0 = moments(r0, x, y)[1] - moments(l0, x, y)[1]
    sep1 = moments(r1, x, y)[1] - moments(l1, x, y)[1]
    assert sep1 / sep0 == pytest.approx(ratio, abs=0.02)
    assert np.abs((l1 + r1) - (l0 + r0)).max() < 1e-6
    assert moments(l1, x, y)[0] == pytest.approx(0.5, abs=1e-5)


@pytest.mark.parametrize("N", [2.0, 4.0])
def test_focus_offset_moves_the_zero_disparity_depth_nearer(N: float) -> None:
    lens = pu.Lens(85.0, N, 1000.0, PITCH)
    c = 24.0 / N  # large enough that pixel binning hardly bends the separation's line
    seps = {}
    for s in (c, -c):
        left, right = point_views(s, "focus_offset", N)
        seps[s] = moments(right, *POINTS[0])[1] - moments(left, *POINTS[0])[1]
    c0 = -c * (seps[c] + seps[-c]) / (seps[c] - seps[-c])  # where the (linear) L-R separation crosses zero
    expect = lens.aperture_mm * pu.EFFECT_DEFAULTS["focus_offset"] / lens.sensor_distance_mm() / PITCH
    assert -c0 == pytest.approx(expect, rel=0.1)  # Eq. 6's CoC where the views agree: the lens focuses nearer
    l0, r0 = point_views(c, "none", N)
    assert abs(moments(r0, *POINTS[0])[1] - moments(l0, *POINTS[0])[1]) == pytest.approx(abs(seps[-c]), rel=0.25)


def _radial(img: np.ndarray, x: int, y: int, radius: float) -> tuple[float, float]:
    """Mean of the green channel within 0.35 radius of (x, y) and in the ring 0.65-0.95 radius."""
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    rr = np.hypot(xx - x, yy - y) / radius
    g = img[..., 1]
    return float(g[rr < 0.35].mean()), float(g[(rr > 0.65) & (rr < 0.95)].mean())


def test_psf_profile_is_centre_heavy_at_equal_size_on_both_sides_of_focus() -> None:
    for c in (12.0, -12.0):
        l0, r0 = point_views(c)
        l1, r1 = point_views(c, "psf_profile")
        centre0, rim0 = _radial(l0 + r0, *POINTS[0], abs(c) / 2)
        centre1, rim1 = _radial(l1 + r1, *POINTS[0], abs(c) / 2)
        assert centre0 == pytest.approx(rim0, rel=0.05)  # the ideal disc is flat
        assert centre1 / rim1 > 1.8  # exp(-1.1 rho^2): rim at ~0.4 of the centre
        assert moments(l1, *POINTS[0])[0] == pytest.approx(0.5, abs=1e-5)  # exposure-normalised
        big = (l1 + r1)[..., 1] > 1e-7
        assert big.sum() == ((l0 + r0)[..., 1] > 1e-7).sum()  # the same support: size unchanged
    # weaker at f/4 (the angle of the marginal ray halves)
    l4, r4 = point_views(6.0, "psf_profile", 4.0)
    c4, rim4 = _radial(l4 + r4, *POINTS[0], 3.0)
    assert 1.0 < c4 / rim4 < centre1 / rim1


def test_front_back_asymmetry_flips_the_profile_between_the_sides_of_focus() -> None:
    fulls = {}
    for c in (10.0, -10.0):
        left, right = point_views(c, "front_back_asymmetry")
        fulls[c] = (left + right, moments(right, *POINTS[0])[1] - moments(left, *POINTS[0])[1])
        l0, r0 = point_views(c)
        clean_sep = moments(r0, *POINTS[0])[1] - moments(l0, *POINTS[0])[1]
        assert fulls[c][1] == pytest.approx(clean_sep, rel=0.01)  # the AF balance keeps the DP disparity
    cb, rb = _radial(fulls[10.0][0], *POINTS[0], 5.0)
    cf, rf = _radial(fulls[-10.0][0], *POINTS[0], 5.0)
    assert cb / rb > 1.15  # under-corrected: behind focus the rim's rays spread out (centre-heavy)
    assert cf / rf < 0.85  # in front they crowd (bright rim)
    # at the recorded focus the rays' mean landing is the same in both views (the AF balance; pupil sampling aside) ...
    optics = pu.optics_of(pu.Lens(85.0, 2.0, 1000.0, PITCH), pu.Effects.of("front_back_asymmetry"))
    ux, uy, _, _ = pu.pupil_lattice(64)
    ex, _ = pu.ray_landing(ux, uy, 0.0, optics.sa3_px, optics.sa5_px, 0.0, 0.0)
    for view in (pu.LEFT, pu.RIGHT):
        m = pu._ray_masses(64, view, 0.0, 0.0)
        assert abs((m * ex).sum() / m.sum()) < 1e-3
    # ... and binning the sub-pixel spot into pixels leaves under 0.1 px of separation at f/2 (none at f/4)
    l0, r0 = point_views(0.0, "front_back_asymmetry")
    assert abs(moments(r0, *POINTS[0])[1] - moments(l0, *POINTS[0])[1]) < 0.1
    l4, r4 = point_views(0.0, "front_back_asymmetry", 4.0)
    assert abs(moments(r4, *POINTS[0])[1] - moments(l4, *POINTS[0])[1]) < 1e-6
    clean = {c: sum(point_views(c)) for c in (10.0, -10.0)}
    assert np.abs(clean[10.0] - clean[-10.0]).max() < 1e-6  # without it both sides are the same disc


def test_misregistration_moves_both_views_against_sharp_by_the_stated_similarity() -> None:
    scene, tex = plane(0.0, seed=5)
    eff = pu.Effects.of("misregistration")
    left, right = pu.render_views(scene, LENS, eff)
    sharp = pu.render_sharp(scene, LENS, eff, 0.0)
    assert np.array_equal(sharp, frame(tex))  # sharp is not moved
    M = pu.misregistration_matrix(eff, SIZE)
    W, H = SIZE
    shift = M @ np.array([(W - 1) / 2, (H - 1) / 2, 1.0]) - np.array([(W - 1) / 2, (H - 1) / 2])
    assert shift == pytest.approx([0.55 * W / 256, -0.35 * W / 256], abs=1e-9)
    for view in (left, right):
        dx, dy = shift_between(sharp, 2 * view)
        assert dx == pytest.approx(shift[0], abs=0.03) and dy == pytest.approx(shift[1], abs=0.03)
    # the content, warped back, is the unmoved view (Lanczos resampling aside)
    back = cv2.warpAffine(left, M, (W, H), flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP)
    l0, _ = pu.render_views(scene, LENS, NONE)
    assert np.abs(back - l0)[6:-6, 6:-6].mean() < 0.01


def shift_between(a: np.ndarray, b: np.ndarray, margin: int = 6) -> tuple[float, float]:
    """Least-squares sub-pixel translation ``d`` with ``b(x) ~ a(x - d)`` (linearised; small shifts)."""
    a = cv2.GaussianBlur(a.mean(-1).astype(np.float64), (0, 0), 1.5)  # smooth: the linearisation holds
    b = cv2.GaussianBlur(b.mean(-1).astype(np.float64), (0, 0), 1.5)
    gy, gx = np.gradient(a)
    m = (slice(margin, -margin), slice(margin, -margin))
    G = np.stack([gx[m].ravel(), gy[m].ravel()], 1)
    d = np.linalg.lstsq(G, (a - b)[m].ravel(), rcond=None)[0]
    return float(d[0]), float(d[1])


@pytest.mark.parametrize("strength", [0.0, 1.0, 2.0])
def test_noise_raises_the_views_variance_by_the_stated_ratio(strength: float) -> None:
    eff = pu.Effects.of({"noise": strength} if strength else "none")
    shot, read = pu.views_noise(eff)
    a = pu.EFFECT_DEFAULTS["noise"] * strength
    assert (shot, read) == pytest.approx((pu.NOMINAL_SHOT_VAR * (1 + a), pu.NOMINAL_READ_SIGMA * (1 + a)))
    img = np.full((300, 300, 3), 0.25, np.float32)
    noisy = pu.add_sensor_noise(np.random.default_rng(1), img, shot, read)
    nominal = pu.NOMINAL_SHOT_VAR * 0.25 + pu.NOMINAL_READ_SIGMA**2
    assert np.var(noisy - img) / nominal == pytest.approx(pu.noise_ratio(strength), rel=0.02)
    if strength == 1.0:
        assert 2.0 < pu.noise_ratio(strength) < 3.0


# ------------------------------------------------------------------------------------------------ occlusion
def test_a_near_layer_hides_the_background_behind_it_unlike_a_scatter_without_occlusion() -> None:
    W, H = SIZE
    hc, wc = H + 2 * PAD, W + 2 * PAD
    c_near = -12.0
    back = np.full((hc, wc, 3), 0.05, np.float32)
    x0, x1, y0, y1 = PAD + 30, PAD + 70, PAD + 14, PAD + 50  # the near card's footprint (canvas px)
    back[y0:y1, x0:x1] = 0.9  # bright only where the near card hides it
    card = np.zeros((hc, wc), np.float32)
    card[y0:y1, x0:x1] = 1.0
    at = lambda c: np.full((hc, wc), LENS.inv_depth_for_coc(c))  # noqa: E731
    layers = [Layer(back, np.ones((hc, wc), np.float32), at(0.0), "back"),
              Layer(np.full((hc, wc, 3), 0.2, np.float32), card, at(c_near), "near")]
    scene = LayerScene(layers, SIZE, PAD)
    left, right = pu.render_views(scene, LENS, NONE)
    r = int(math.ceil(abs(c_near) / 2)) + 1
    inner = (slice(y0 - PAD + r, y1 - PAD - r), slice(x0 - PAD + r, x1 - PAD - r))
    for view in (left, right):
        assert np.abs(view[inner] - 0.1).max() < 1e-5  # only the card: its colour's half, nothing of what it hides
    # a scatter without occlusion would add the hidden bright patch's light there
    alone = [pu.render_views(LayerScene([layer], SIZE, PAD), LENS, NONE)[0] for layer in layers]
    assert (alone[0] + alone[1])[inner].min() > 0.4
    # at the card's blurred rim the background shows through only by the share of rays that pass the card
    yc = (y0 + y1) // 2 - PAD
    edge_in = left[yc, x0 - PAD + 1, 1]
    assert 0.1 < edge_in < 0.45
    # DP occlusion is asymmetric: in front of focus the left view sees past the card's left edge less than the right
    assert abs(left[yc, x0 - PAD - 2, 1] - right[yc, x0 - PAD - 2, 1]) > 0.01


# ------------------------------------------------------------------------------------------------ writer
@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("pupil")
    out = {"clean": root / "clean", "all": root / "all", "quiet": root / "quiet"}
    kw = dict(scenes=3, size=(64, 44), seed=7)
    pu.write_dataset(out["clean"], "none", **kw)
    pu.write_dataset(out["all"], list(EFFECT_NAMES), **kw)
    pu.write_dataset(out["quiet"], "none", noise=False, **kw)
    return out


def test_the_writer_writes_format_v1_split_by_scene_with_planted_json(written: dict[str, Path]) -> None:
    for name in ("clean", "all"):
        root = written[name]
        reader = DatasetReader(root)
        index = json.loads((root / "dataset.json").read_text())
        assert index["format"] == "dp5k-dataset" and index["version"] == 1
        splits = index["splits"]
        assert [len(splits[s]) for s in ("train", "val", "test")] == [2, 2, 2]
        scenes = {s: {pid.split("_")[0] for pid in ids} for s, ids in splits.items()}
        tr, va, te = scenes["train"], scenes["val"], scenes["test"]
        assert not (tr & va or tr & te or va & te)
        for pid in sum(splits.values(), []):
            pair = reader.load(pid)
            p = json.loads((root / "pairs" / pid / "params.json").read_text())
            assert p["sharp_f_number"] == 22.0 and p["image_size"] == [64, 44] and pair.sharp.shape == (44, 64, 3)
            assert np.isfinite(pair.coc_px).all() and pair.valid.all()
            F = p["focus_distance_mm"]
            fx, fy = p["focus_point_px"]
            assert pair.depth_mm[fy, fx] == pytest.approx(F, abs=0.5)
            assert abs(pair.coc_px[fy, fx]) < 0.01  # the focus point is on the recorded focus
            assert "effects" not in p  # what was planted is only in planted.json
        planted = json.loads((root / "planted.json").read_text())
        assert planted["generator"] == "dp5k_testing.pupil_dp"
        assert set(planted["effects"]) == (set(EFFECT_NAMES) if name == "all" else set())
        if name == "all":
            assert planted["effects"]["noise"] == pu.EFFECT_DEFAULTS["noise"]


def test_the_scenes_and_labels_do_not_depend_on_what_is_planted(written: dict[str, Path]) -> None:
    a, b = DatasetReader(written["clean"]), DatasetReader(written["all"])
    ids = json.loads((written["clean"] / "dataset.json").read_text())["splits"]
    assert ids == json.loads((written["all"] / "dataset.json").read_text())["splits"]
    for pid in sum(ids.values(), []):
        pa, pb = a.load(pid), b.load(pid)
        assert np.array_equal(pa.depth_mm, pb.depth_mm) and np.array_equal(pa.coc_px, pb.coc_px)
        assert not np.array_equal(pa.left, pb.left)


def test_the_writer_adds_the_nominal_noise_and_never_overwrites(written: dict[str, Path]) -> None:
    a, q = DatasetReader(written["clean"]), DatasetReader(written["quiet"])
    pid = json.loads((written["clean"] / "dataset.json").read_text())["splits"]["train"][0]
    pa, pq = a.load(pid), q.load(pid)
    for noisy, clean in ((pa.left, pq.left), (pa.sharp, pq.sharp)):
        expect = pu.NOMINAL_SHOT_VAR * clean.mean() + pu.NOMINAL_READ_SIGMA**2
        assert np.var(noisy - clean) / expect == pytest.approx(1.0, rel=0.15)
    before = sorted(p.name for p in written["clean"].rglob("*"))
    with pytest.raises(FileExistsError):
        pu.write_dataset(written["clean"], "none", scenes=3, size=(64, 44))
    assert sorted(p.name for p in written["clean"].rglob("*")) == before
    with pytest.raises(ValueError, match="at least 3 scenes"):
        pu.write_dataset(written["clean"].parent / "two", "none", scenes=2, size=(64, 44))
    assert not (written["clean"].parent / "two").exists()


def test_the_renderer_shares_no_code_with_dp5k() -> None:
    """Its modules import only the standard library, numpy, OpenCV, tifffile and each other (not dp5k, not the other
    renderers): an independent implementation of the physics."""
    allowed = {"json", "math", "os", "shutil", "string", "functools", "dataclasses", "pathlib", "typing", "__future__",
               "cv2", "numpy", "tifffile"}
    for path in (Path(pu.__file__), Path(pu.__file__).with_name("pupil_scene.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                assert {a.name.split(".")[0] for a in node.names} <= allowed, (path.name, ast.dump(node))
            elif isinstance(node, ast.ImportFrom):
                ok = node.module.split(".")[0] in allowed if node.level == 0 else node.module == "pupil_scene"
                assert ok, (path.name, node.module)
