"""The focus check (DP disparity, sharpness and shift in the focus window) and the simulated effects it must catch:
repeated AFs land elsewhere, the view can move. Frames come from the simulated bodies' own optics: the flat world
(a crop of a 5D Mark IV sensor, 5.36 um pixels, Eq. 6 defocus) and, for noise, the studio at its small scale."""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import pytest

from dp5k_capture.focus_check import FocusThresholds, compare_focus, dp_disparity_px, focus_window
from dp5k_capture.sim.eos_body import AF_SCATTER_REL, ExposureSettings, SimulatedEOS
from dp5k_capture.sim.world import FlatOptics
from dp5k_common.rawfile import DualPixelFrames, read_dual_pixel

POINT = (24, 16)


def _frames(data: bytes) -> DualPixelFrames:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "f.dng"
        path.write_bytes(data)
        return read_dual_pixel(path)


def _flat(optics: FlatOptics, focus_m: float, f_number: float = 1.8) -> DualPixelFrames:
    return _frames(optics.expose(ExposureSettings("S", f_number, 1 / 500, 100, POINT, focus_m, True, 1)))


def test_window_is_the_eq5_window_doubled_and_clipped() -> None:
    assert focus_window((3360, 2240), (6720, 4480)) == (3240, 2160, 240, 160)  # 120 x 80 raw px (30 x 20 at 1680) x 2
    assert focus_window((2, 2), (48, 32)) == (0, 0, 32, 32)  # at least 32 x 32, inside the frame, even (Bayer quads)
    assert focus_window((47, 31), (336, 224))[:2] == (30, 14)


def test_dp_disparity_follows_the_coc_sign_and_size() -> None:
    optics = FlatOptics((48, 32))
    subject = optics.autofocus_m("S", POINT)
    window = focus_window(POINT, (48, 32))
    for rel in (-0.01, -0.003, 0.0, 0.003, 0.01):
        focus = subject * (1 + rel)
        expected = 4 / (3 * np.pi) * float(optics.coc_px(1.8, focus)[POINT[0]])  # docs/conventions.md
        assert dp_disparity_px(_flat(optics, focus), window) == pytest.approx(expected, abs=0.08)
    assert dp_disparity_px(_flat(optics, subject * 1.01), window) < 0  # focused behind the subject: it is in front


def test_a_moved_focus_is_caught_and_an_unchanged_one_is_not() -> None:
    optics = FlatOptics((48, 32))
    subject = optics.autofocus_m("S", POINT)
    kept = _flat(optics, subject)
    same = compare_focus(kept, _flat(optics, subject), POINT)
    assert not same.moved and not same.view_moved and abs(same.dp_disparity_change_px) < 0.02
    for rel in (AF_SCATTER_REL[0], -AF_SCATTER_REL[0], AF_SCATTER_REL[1]):  # the smallest scatter of a repeated AF
        moved = compare_focus(kept, _flat(optics, subject * (1 + rel)), POINT)
        assert moved.moved and not moved.view_moved and abs(moved.dp_disparity_change_px) > FocusThresholds().dp_disparity_px
        assert np.sign(moved.dp_disparity_change_px) == -np.sign(rel) and "DP disparity" in moved.reason


def test_a_shifted_view_and_a_blank_window_are_reported() -> None:
    optics = FlatOptics((48, 32))
    subject = optics.autofocus_m("S", POINT)
    kept = _flat(optics, subject)
    optics.albedo = np.roll(optics.albedo, 2, axis=1)  # the scene (or the body) moved 2 px
    shifted = compare_focus(kept, _flat(optics, subject), POINT)
    assert shifted.view_moved and shifted.shift_px[0] == pytest.approx(2.0, abs=0.1) and abs(shifted.shift_px[1]) < 0.1
    optics.albedo = np.full_like(optics.albedo, 0.5)  # nothing to align on
    blank = compare_focus(_flat(optics, subject), _flat(optics, subject), POINT)
    assert blank.moved and "too little texture" in blank.reason


def test_studio_noise_alone_stays_well_below_the_limits() -> None:
    """Two exposures of the studio at its small scale (336 x 224 raw, sensor noise), same focus: the check keeps them;
    a 3 % focus move (about 0.26 raw px of DP disparity at that scale) is caught."""
    from dp5k_capture.sim.world import StudioOptics

    class Dark:
        def lit_image(self) -> None:
            return None

    studio = StudioOptics("demo01", Dark(), "small", 0)  # type: ignore[arg-type]
    serial, point = studio.serials[0], studio.focus_points_px[0]
    subject = studio.autofocus_m(serial, point)

    def shot(focus: float, seq: int) -> DualPixelFrames:
        return _frames(studio.expose(ExposureSettings(serial, 1.8, 1 / 500, 100, point, focus, True, seq)))

    kept = shot(subject, 1)
    same = compare_focus(kept, shot(subject, 2), point)
    assert not same.moved and abs(same.dp_disparity_change_px) < 0.05 and abs(same.sharpness_ratio - 1) < 0.03
    assert np.hypot(*same.shift_px) < 0.05
    assert compare_focus(kept, shot(subject * 1.03, 3), point).moved


def test_every_af_after_the_first_lands_elsewhere_seeded() -> None:
    def landings(seed: int, run: int) -> list[float]:
        body = SimulatedEOS("SIMX", FlatOptics((48, 32)), af_seed=seed, run=run)
        out = []
        for _ in range(4):
            body._autofocus(POINT)
            out.append(body.focus_distance_m)
        return out

    subject = FlatOptics((48, 32)).autofocus_m("SIMX", POINT)
    first = landings(0, 0)
    assert first[0] == subject  # the body's first AF lands on the subject
    rel = np.abs(np.array(first[1:]) / subject - 1)
    assert np.all((rel >= AF_SCATTER_REL[0]) & (rel <= AF_SCATTER_REL[1])) and len(set(first)) == 4
    assert landings(0, 0) == first  # seeded
    later = landings(0, 1)  # a body of a later in-process run: even its first AF lands elsewhere
    assert later[0] != subject and later != first and landings(1, 0)[1:] != first[1:]


def test_a_plain_focus_window_grows_until_the_change_is_measurable() -> None:
    """A plain surface (a shading ramp, no texture) at the AF point: the check measures in a grown window, where a
    0.3 % refocus still shows and noise-free frames at one focus do not."""
    optics = FlatOptics((96, 64))
    point = (48, 32)
    yy, xx = np.mgrid[0:64, 0:96]
    plain = (np.abs(xx - 48) < 20) & (np.abs(yy - 32) < 20)
    optics.albedo = np.where(plain, 0.4 + 0.2 * xx / 96, optics.albedo)  # a ramp: light falling off, no texture

    rng = np.random.default_rng(5)

    def shot(focus: float) -> DualPixelFrames:  # with sensor noise (the flat world has none): 1 % of the signal
        f = _frames(optics.expose(ExposureSettings("S", 1.8, 1 / 500, 100, point, focus, True, 1)))
        sd = 0.01 * float(f.main.mean() - f.black_level)
        aux = f.aux + rng.normal(0, sd / np.sqrt(2), f.aux.shape)
        main = aux + (f.main.astype(float) - f.aux) + rng.normal(0, sd / np.sqrt(2), f.aux.shape)
        return dataclasses.replace(f, main=main.astype(np.float32), aux=aux.astype(np.float32))

    subject = optics.autofocus_m("S", point)
    kept = shot(subject)
    same = compare_focus(kept, shot(subject), point)
    assert not same.moved and same.window_px[2] > 32 and "the focus window holds too little texture" in same.reason
    assert same.dp_disparity_change_sigma_px <= FocusThresholds().dp_disparity_px / 3
    moved = compare_focus(kept, shot(subject * (1 + AF_SCATTER_REL[0])), point)
    assert moved.moved and moved.window_px == same.window_px
