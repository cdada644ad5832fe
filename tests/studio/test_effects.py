"""Each planted effect changes what it claims to change, and nothing else."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from dp5k_studio import EffectSet, effect_parameters, left_kernel, pair_from_rgbd, parse_effect, render_dp
from dp5k_studio.dataset import NOISE_READ, NOISE_SHOT
from dp5k_studio.dp_optics import coc_channels_px, fourier_shift
from dp5k_common.effects import EFFECT_NAMES
from dp5k_common.errors import BadInputError
from dp5k_common.optics import coc_diameter_px

from .helpers import PITCH_MM, dot_views, lens, moments, textured

BEHIND_MM = 4000.0  # a depth behind the 2 m focus


def _pair(effects: EffectSet | None, depth_mm: float = BEHIND_MM, H: int = 96, W: int = 128):
    img = textured(H, W, 3)
    return render_dp(img, np.full((H, W), depth_mm), lens(1.8, 2000.0), effects)


def test_effect_parsing_and_vocabulary() -> None:
    assert parse_effect("noise=2.5") == ("noise", 2.5)
    assert parse_effect("misregistration") == ("misregistration", 1.0)
    for bad in ("nonsense=1", "noise=abc", "noise=-1"):
        with pytest.raises(BadInputError):
            parse_effect(bad)
    assert not EffectSet()  # off by default
    for name in EFFECT_NAMES:
        params = EffectSet.of(**{name: 1.0}).to_json((288, 192))[name]
        assert params["strength"] == 1.0 and len(params) > 1


@pytest.mark.parametrize("name", ["lr_gain_imbalance", "field_varying_psf", "disparity_scale", "psf_profile", "front_back_asymmetry"])
def test_in_focus_sum_is_untouched_by_effects_that_do_not_claim_it(name: str) -> None:
    base = _pair(None, depth_mm=2000.0)
    eff = _pair(EffectSet.of(**{name: 1.0}), depth_mm=2000.0)
    assert np.allclose(base.left + base.right, eff.left + eff.right, atol=1e-5)


def test_misregistration_shifts_views_without_changing_blur_or_brightness() -> None:
    s = 1.5
    base = _pair(None)
    eff = _pair(EffectSet.of(misregistration=s))
    H, W = base.left.shape[:2]
    dx, dy = effect_parameters("misregistration", s, (W, H))["shift_px"]
    win = cv2.createHanningWindow((W, H), cv2.CV_64F)
    # the shift is band-limited and exact: an integer shift equals np.roll ...
    img = textured(H, W, 4)
    assert np.allclose(fourier_shift(img, 2.0, -1.0)[8:-8, 8:-8], np.roll(img, (-1, 2), (0, 1))[8:-8, 8:-8], atol=1e-5)
    for b, e in ((base.left, eff.left), (base.right, eff.right)):
        # ... and the effect's views are the ideal views shifted by the documented amount
        assert np.allclose(e, fourier_shift(b, dx, dy), atol=1e-5)
        inner = (slice(10, -10), slice(10, -10))
        assert e[inner].mean() == pytest.approx(b[inner].mean(), rel=2e-3)
        # blur unchanged: same amplitude spectrum (a shift only changes phase)
        fb = np.abs(np.fft.fft2(b[:, :, 1] * win))
        fe = np.abs(np.fft.fft2(e[:, :, 1] * win))
        assert np.abs(fb - fe).sum() / fb.sum() < 0.03
    # the DP disparity between the views is unchanged
    _, xl0, _, _, _ = moments(dot_views(BEHIND_MM, lens()).left[:, :, 1])
    d0 = dot_views(BEHIND_MM, lens())
    d1 = dot_views(BEHIND_MM, lens(), EffectSet.of(misregistration=s))
    sep = lambda d: moments(np.clip(d.right[:, :, 1], 0, None))[1] - moments(np.clip(d.left[:, :, 1], 0, None))[1]  # noqa: E731
    assert sep(d1) == pytest.approx(sep(d0), abs=0.05)


def test_lr_gain_imbalance_sets_the_documented_ratio_across_the_field() -> None:
    eff = _pair(EffectSet.of(lr_gain_imbalance=1.0), depth_mm=2000.0)
    H, W = eff.left.shape[:2]
    ratio = (eff.left / eff.right)[:, :, 1]
    mid = H // 2
    xn = (np.arange(W) + 0.5) / W * 2 - 1
    yn = (mid + 0.5) / H * 2 - 1
    want = np.exp(0.18 + 0.10 * xn - 0.06 * yn**2)
    assert np.allclose(ratio[mid], want, rtol=1e-4)
    assert ratio[mid, W // 2] == pytest.approx(1.2, abs=0.01)  # Pixel 4 scenes: 1.18..1.24
    # defocus and disparity unchanged
    d0 = dot_views(BEHIND_MM, lens())
    d1 = dot_views(BEHIND_MM, lens(), EffectSet.of(lr_gain_imbalance=1.0))
    for v0, v1 in ((d0.left, d1.left), (d0.right, d1.right)):
        m0, x0, _, vx0, _ = moments(v0[:, :, 1])
        m1, x1, _, vx1, _ = moments(v1[:, :, 1])
        assert x1 == pytest.approx(x0, abs=0.02) and vx1 == pytest.approx(vx0, rel=0.01)
        assert m1 != pytest.approx(m0, rel=0.02)  # but the brightness is changed


@pytest.mark.parametrize("s", [1.0, 4.0])
def test_disparity_scale_shrinks_disparity_keeps_sum(s: float) -> None:
    d0 = dot_views(BEHIND_MM, lens())
    d1 = dot_views(BEHIND_MM, lens(), EffectSet.of(disparity_scale=s))
    sep = lambda d: moments(d.right[:, :, 1])[1] - moments(d.left[:, :, 1])[1]  # noqa: E731
    assert sep(d1) == pytest.approx(sep(d0) / (1.0 + s), rel=0.01)
    assert np.allclose(d0.left + d0.right, d1.left + d1.right, atol=1e-7)
    assert moments(d1.left[:, :, 1])[0] == pytest.approx(0.5, rel=1e-3)


def test_field_varying_psf_grows_blur_off_axis_and_softens_the_split() -> None:
    eff = EffectSet.of(field_varying_psf=1.0)
    H, W = 161, 321
    centre, edge = (80, 160), (80, 25)
    blur = {}
    for where in (centre, edge):
        for name, e in (("off", None), ("on", eff)):
            d = dot_views(BEHIND_MM, lens(), e, at=where, shape=(H, W))
            full = (d.left + d.right)[:, :, 1]
            blur[where, name] = (moments(full)[3], moments(d.right[:, :, 1])[1] - moments(d.left[:, :, 1])[1])
    xn = (25 + 0.5) / W * 2 - 1
    yn = (80 + 0.5) / H * 2 - 1
    growth = 1 + 0.30 * (xn**2 + yn**2) / 2
    # a layer blurs with its pixels' mean CoC: bins are 8 % wide, so a smoothly varying CoC is within
    # +-4 % (+-8 % in variance) of its exact value
    assert blur[centre, "on"][0] == pytest.approx(blur[centre, "off"][0], rel=0.09)
    assert blur[edge, "on"][0] / blur[edge, "off"][0] == pytest.approx(growth**2, rel=0.09)
    assert blur[edge, "on"][0] > 1.15 * blur[centre, "on"][0]
    # disparity at the side is smaller than its blur alone would give (the soft split)
    assert blur[edge, "on"][1] < 0.9 * blur[edge, "off"][1] * growth
    assert blur[centre, "on"][1] == pytest.approx(blur[centre, "off"][1], rel=0.05)


def test_chromatic_defocus_shifts_red_and_blue_focus_only() -> None:
    pitch = 36.0 / 1680
    L = lens(1.8, 2000.0, pitch)
    c = coc_channels_px(np.array([[2000.0]]), L, EffectSet.of(chromatic_defocus=1.0))[0, 0]
    v = 1.0 / (1.0 / 85.0 - 1.0 / 2000.0)
    expect = (85.0 / 1.8) * (v / 85.0) ** 2 * 0.04 / v / pitch  # A * dv / v, dv = (v / f)^2 df
    assert c[1] == pytest.approx(0.0, abs=1e-9)
    assert c[0] == pytest.approx(-expect, rel=0.05) and c[2] == pytest.approx(expect, rel=0.05)
    # rendered: green identical to the ideal lens, red and blue blurred at the focus distance
    eff = EffectSet.of(chromatic_defocus=3.0)
    d0 = dot_views(2000.0, L)
    d1 = dot_views(2000.0, L, eff)
    assert np.allclose(d0.left[:, :, 1], d1.left[:, :, 1], atol=1e-7)
    for ch in (0, 2):
        assert moments((d1.left + d1.right)[:, :, ch])[3] > moments((d0.left + d0.right)[:, :, ch])[3] + 0.3


def test_psf_profile_brightens_the_rim_same_support_and_energy() -> None:
    d0 = dot_views(BEHIND_MM, lens(), full=True)
    d1 = dot_views(BEHIND_MM, lens(), EffectSet.of(psf_profile=1.0), full=True)
    f0, f1 = d0.full[:, :, 1], d1.full[:, :, 1]
    assert f1.sum() == pytest.approx(f0.sum(), rel=1e-5)
    assert ((f1 > 1e-6) == (f0 > 1e-6)).mean() > 0.999  # same disc
    assert moments(f1)[3] > 1.1 * moments(f0)[3]  # mass moved to the rim
    assert np.allclose(d1.right[:, :, 1], d1.left[:, ::-1, 1], atol=1e-7)  # still mirror-symmetric


def test_front_back_asymmetry_breaks_only_front_back_symmetry() -> None:
    c = 14.0
    for eff, asym in ((None, False), (EffectSet.of(front_back_asymmetry=1.0), True)):
        back = left_kernel(c, eff)
        front = left_kernel(-c, eff)
        diff = np.abs(front - back[:, ::-1]).sum() / back.sum()
        assert (diff > 0.15) if asym else (diff < 0.03)
    # front blur is 10 % larger at s = 1 (depths with equal and opposite Eq. 6 CoC)
    F = 2000.0
    d_front = 1.0 / (2.0 / F - 1.0 / BEHIND_MM)
    c_b = float(coc_diameter_px(BEHIND_MM, F, 85.0, 1.8, PITCH_MM))
    c_f = float(coc_diameter_px(d_front, F, 85.0, 1.8, PITCH_MM))
    assert c_f == pytest.approx(-c_b, rel=1e-9)
    eff = EffectSet.of(front_back_asymmetry=1.0)

    def radius(psf: np.ndarray) -> float:
        yy, xx = np.nonzero(psf > 1e-4 * psf.max())
        return float(np.hypot(xx - psf.shape[1] // 2, yy - psf.shape[0] // 2).max())

    r_front = radius((lambda d: d.left + d.right)(dot_views(d_front, lens(), eff))[:, :, 1])
    r_back = radius((lambda d: d.left + d.right)(dot_views(BEHIND_MM, lens(), eff))[:, :, 1])
    assert r_back == pytest.approx(abs(c_b) / 2, abs=1.5)
    assert r_front == pytest.approx(1.1 * abs(c_b) / 2, abs=1.5)


def test_focus_offset_moves_true_focus_but_not_the_recorded_one() -> None:
    H, W = 64, 96
    pitch = 36.0 / 1680
    img = np.zeros((H, W, 3), np.float32)
    img[32, 48] = 1.0
    depth = np.full((H, W), 2000.0)
    for s, blurred in ((0.0, False), (1.0, True)):
        rp = pair_from_rgbd(img, depth, f_number=1.8, focus_distance_mm=2000.0, pixel_pitch_mm=pitch,
                            effects=EffectSet.of(focus_offset=s) if s else None, noise=False)
        assert np.allclose(rp.coc_px, 0.0, atol=1e-6)  # coc.tif uses the recorded focus
        assert rp.extra["true_focus_distance_mm"] == pytest.approx(2000.0 * (1 + 0.05 * s))
        var = moments((rp.left + rp.right)[:, :, 1])[3]
        if blurred:
            c = float(coc_diameter_px(2000.0, 2100.0, 85.0, 1.8, pitch))
            assert 4 * math.sqrt(var - 1 / 6) == pytest.approx(abs(c), rel=0.1)
        else:
            assert var < 1e-6


def test_noise_effect_raises_signal_dependent_noise() -> None:
    H, W = 128, 128
    img = np.full((H, W, 3), 0.6, np.float32)
    depth = np.full((H, W), 2000.0)
    out = {}
    for s in (0.0, 1.0):
        rp = pair_from_rgbd(img, depth, f_number=2.8, focus_distance_mm=2000.0, pixel_pitch_mm=PITCH_MM,
                            effects=EffectSet.of(noise=s) if s else None, rng=np.random.default_rng(5))
        out[s] = rp.left[:, :, 1]
    for s, a in out.items():
        want = NOISE_SHOT * (1 + 3 * s) * 0.3 + (NOISE_READ * (1 + s)) ** 2
        assert a.mean() == pytest.approx(0.3, abs=1e-3)
        assert a.var() == pytest.approx(want, rel=0.08)


def test_misregistration_in_the_raw_route_moves_only_dp_captures() -> None:
    from dp5k_studio import Studio, make_rig, make_scene

    rig = make_rig(40)
    ideal = Studio(make_scene("boxes", rig), rig, supersample=1)
    shifted = Studio(make_scene("boxes", rig), rig, EffectSet.of(misregistration=2.0), supersample=1)
    F = ideal.focus_distance_m(0, ideal.focus_point_px(0))
    sharp_a, sharp_b = ideal.render_views(0, 22.0, F), shifted.render_views(0, 22.0, F)
    assert np.array_equal(sharp_a.left, sharp_b.left)  # the sharp frame defines the geometry: untouched
    dp_a, dp_b = ideal.render_views(0, 2.8, F), shifted.render_views(0, 2.8, F)
    H, W = dp_a.left.shape[:2]
    dx, dy = effect_parameters("misregistration", 2.0, (W, H))["shift_px"]
    assert np.allclose(dp_b.left, fourier_shift(dp_a.left, dx, dy), atol=1e-5)


@pytest.mark.parametrize("name", EFFECT_NAMES)
def test_every_effect_acts_in_both_routes_and_is_recorded(name: str) -> None:
    from dp5k_studio import Studio, make_rig, make_scene

    rig = make_rig(60)
    eff = EffectSet.of(**{name: 1.5})
    shots = []
    for e in (None, eff):
        st = Studio(make_scene("boxes", rig), rig, e, supersample=1)
        F = st.focus_distance_m(0, st.focus_point_px(0))
        shots.append(st.expose(0, 2.8, F, 1 / 100, 400, rng=np.random.default_rng(7)))
    assert not (np.array_equal(shots[0].main, shots[1].main) and np.array_equal(shots[0].aux, shots[1].aux))
    assert name in shots[1].metadata["effects"] and not shots[0].metadata["effects"]
    img = textured(48, 64, 9)
    depth = np.tile(np.linspace(900.0, 4000.0, 64), (48, 1))
    kw = dict(f_number=2.8, focus_distance_mm=1500.0, pixel_pitch_mm=36.0 / 640, rng=None)
    a = pair_from_rgbd(img, depth, **{**kw, "rng": np.random.default_rng(1)})
    b = pair_from_rgbd(img, depth, effects=eff, **{**kw, "rng": np.random.default_rng(1)})
    assert not np.array_equal(a.left, b.left) or not np.array_equal(a.right, b.right)
    assert name in b.extra["effects"]
