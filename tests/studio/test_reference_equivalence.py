"""Equivalence of the studio's optimised paths with their reference implementations (``tests/reference``).

Each optimised path is compared with its reference on a small scene with hidden surfaces: the depth plan +
per-radiance render (``dp_image_formation``), a plan reused for other radiance images, the structured-light frames
formed from the dark / full-light / complement views (pattern_views.py), the pinhole radiance
(``pinhole_radiance``) and the raw sensor (``raw_sensor``).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dp5k_capture.patterns import projection
from dp5k_studio import EffectSet, LensSetting, Studio, make_rig, make_scene, render_dp
from dp5k_studio.dp_optics import plan_dp
from dp5k_studio.sensor import expose_raw
from dp5k_studio.studio import diffraction_sigma_px

from ..reference import dp_image_formation, pinhole_radiance, raw_sensor

TOL = 1e-4
"""Largest allowed difference of linear radiance (white paper ~ 0.85)."""
PLANTED = EffectSet.of(chromatic_defocus=1.0, field_varying_psf=1.0, psf_profile=1.0, misregistration=1.0,
                       lr_gain_imbalance=1.0, disparity_scale=1.0, front_back_asymmetry=1.0)


@pytest.fixture(scope="module")
def studio() -> Studio:
    rig = make_rig("small")
    return Studio(make_scene("demo01", rig), rig, seed=0)


def _lens(st: Studio, f_number: float) -> LensSetting:
    cam = st.rig.cameras[0]
    return LensSetting(cam.focal_length_mm, f_number, st.focus_distance_m(0, st.focus_point_px(0)) * 1000.0, cam.pixel_pitch_mm)


def _max_diff(a, b) -> float:
    return max(float(np.abs(np.asarray(x) - np.asarray(y)).max()) for x, y in zip(a, b))


@pytest.mark.parametrize("f_number,effects", [(1.8, None), (22.0, None), (1.8, PLANTED)])
def test_plan_render_equals_the_reference(studio: Studio, f_number: float, effects: EffectSet | None) -> None:
    g = studio.geometry(0)
    hidden = (g.hidden_radiance(None), g.hidden["depth_m"] * 1000.0)
    lens = _lens(studio, f_number)
    new = render_dp(studio.radiance(0), g.depth_m * 1000.0, lens, effects, full=True, hidden=hidden)
    want_views = dp_image_formation.render_dp(studio.radiance(0), g.depth_m * 1000.0, lens, effects, full=True, hidden=hidden)
    assert float(np.abs(want_views.left - want_views.right).max()) > 0.01  # the views differ: the comparison is not vacuous
    assert _max_diff((new.left, new.right, new.full), (want_views.left, want_views.right, want_views.full)) <= TOL


def test_a_plan_reused_for_other_radiance_equals_fresh_renders(studio: Studio) -> None:
    g = studio.geometry(0)
    lens = _lens(studio, 2.8)
    plan = plan_dp(g.depth_m * 1000.0, lens, None, g.hidden["depth_m"] * 1000.0)
    for k in (3, 4, 44):
        pat = projection(k, 1920, 1200).astype(np.float32) / 255.0
        rad, hid = g.radiance(pat), g.hidden_radiance(pat)
        got = plan.render(rad, hid)
        want = dp_image_formation.render_dp(rad, g.depth_m * 1000.0, lens, None, hidden=(hid, g.hidden["depth_m"] * 1000.0))
        assert _max_diff((got.left, got.right), (want.left, want.right)) <= TOL


def test_structured_light_frames_equal_direct_renders(studio: Studio) -> None:
    """Black, white, a Gray-code pair (the - frame formed from the + frame), a grey level and a colour image
    in the order a capture shows them, against the reference render of each frame's radiance."""
    g = studio.geometry(0)
    F_m = studio.focus_distance_m(0, studio.focus_point_px(0))
    lens = _lens(studio, 22.0)
    sig = diffraction_sigma_px(22.0, studio.rig.cameras[0].pixel_pitch_mm)
    rng = np.random.default_rng(0)
    images = [projection(k, 1920, 1200) for k in (6, 7, 44, 45, 8, 9)]
    images += [np.full((1200, 1920), 128, np.uint8), rng.integers(0, 256, (1200, 1920, 3), dtype=np.uint8), None]
    seen = []
    for img in images:
        studio.set_projector_image(img)
        got = studio.render_views(0, 22.0, F_m)
        pat = None if img is None else img.astype(np.float32) / 255.0
        reference = pinhole_radiance.ReferenceGeometry(g)
        want_views = dp_image_formation.render_dp(reference.radiance(pat), g.depth_m * 1000.0, lens, studio.effects_at(22.0),
                                                  hidden=(reference.hidden_radiance(pat), g.hidden["depth_m"] * 1000.0))
        want = [cv2.GaussianBlur(v, (0, 0), sig, borderType=cv2.BORDER_REFLECT) for v in (want_views.left, want_views.right)]
        assert _max_diff((got.left, got.right), want) <= TOL
        seen.append(float(got.left.mean()))
    studio.set_projector_image(None)
    assert seen[2] > seen[0] > seen[3] and seen[2] > seen[1] > seen[3]  # white > pattern > black: the frames differ


@pytest.mark.parametrize("supersample", [1, 2])
def test_radiance_equals_the_reference(supersample: int) -> None:
    rig = make_rig("small")
    g = Studio(make_scene("boxes", rig), rig, supersample=supersample).geometry(1)
    r = pinhole_radiance.ReferenceGeometry(g)
    rng = np.random.default_rng(1)
    for pat in (None, projection(10, 1920, 1200).astype(np.float32) / 255.0, rng.random((1200, 1920, 3), dtype=np.float32)):
        assert np.array_equal(g.radiance(pat), r.radiance(pat))
        assert np.array_equal(g.hidden_radiance(pat), r.hidden_radiance(pat))


@pytest.mark.parametrize("shot_var_factor", [1.0, 4.0])
def test_raw_sensor_equals_the_reference(studio: Studio, shot_var_factor: float) -> None:
    v = studio.render_views(0, 4.0, 2.0)
    new = expose_raw(v.left, v.right, 4.0, 0.01, 100, np.random.default_rng(3), shot_var_factor=shot_var_factor)
    want_views = raw_sensor.expose_raw(v.left, v.right, 4.0, 0.01, 100, np.random.default_rng(3), shot_var_factor=shot_var_factor)
    assert np.array_equal(new[0], want_views[0]) and np.array_equal(new[1], want_views[1])
