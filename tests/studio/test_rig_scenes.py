"""The rig (paper hardware, scales, extrinsics) and the scenes (presets, determinism, depth statistics)."""

from __future__ import annotations

import numpy as np
import pytest

from dp5k_studio import PRESETS, Studio, make_rig, make_scene
from dp5k_studio.render import view_geometry
from dp5k_common.errors import BadInputError


@pytest.mark.parametrize("scale,size", [("small", (336, 224)), ("medium", (1344, 896)), ("paper", (3360, 2240)), (40, (168, 112))])
def test_rig_scales_and_intrinsics(scale, size) -> None:
    rig = make_rig(scale)
    for cam in rig.cameras:
        assert (cam.width, cam.height) == size
        assert cam.pixel_pitch_mm == pytest.approx(36.0 / size[0])
        assert cam.sensor_size_mm == (36.0, 24.0) and cam.focal_length_mm == 85.0
        # pinhole focal length = thin-lens image distance at the 2.7 m reference focus (Eq. 7)
        v_mm = 1.0 / (1.0 / 85.0 - 1.0 / 2700.0)
        assert cam.K[0, 0] * cam.pixel_pitch_mm == pytest.approx(v_mm)
        assert np.allclose(cam.R @ cam.R.T, np.eye(3)) and np.allclose(cam.dist, 0)
    assert (rig.projector.width, rig.projector.height) == (1920, 1200)
    assert [c.name for c in rig.cameras] == ["cam0", "cam1"]


def test_rig_baseline_and_convergence() -> None:
    rig = make_rig("small", baseline_m=0.25)
    R, T = rig.stereo_RT()
    assert np.linalg.norm(T) == pytest.approx(0.25)
    c0, c1 = (c.center_m for c in rig.cameras)
    assert c0[0] < 0 < c1[0]  # cam0 is the left body
    # both optical axes meet in front of the rig
    z0, z1 = rig.cameras[0].R[2], rig.cameras[1].R[2]
    assert z0[0] > 0 > z1[0]
    jittered = make_rig("small", seed=3)
    assert not np.allclose(jittered.cameras[0].R, rig.cameras[0].R)


def test_bad_scale_is_a_clear_error() -> None:
    with pytest.raises(BadInputError):
        make_rig("huge")
    with pytest.raises(BadInputError):
        make_rig(0.5)


def test_presets_build_and_unknown_name_fails() -> None:
    rig = make_rig(40)
    for name in PRESETS:
        sc = make_scene(name, rig)
        g = view_geometry(sc, rig.cameras[0], None, (), 1)
        assert np.isfinite(g.depth_m).mean() > 0.99, name
    with pytest.raises(BadInputError):
        make_scene("no-such-scene", rig)


def test_scenes_are_deterministic() -> None:
    rig = make_rig(40)
    a = Studio(make_scene(7, rig), rig, supersample=1).radiance(0)
    b = Studio(make_scene("7", rig), rig, supersample=1).radiance(0)
    c = Studio(make_scene(8, rig), rig, supersample=1).radiance(0)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_random_scene_depth_statistics_follow_the_paper() -> None:
    """Paper Fig. 5: depth 0.264 .. 10 m, mean 3.02 m, median 2.77 m."""
    rig = make_rig(60)
    z = np.concatenate([view_geometry(make_scene(s, rig), rig.cameras[0], None, (), 1).depth_m.ravel() for s in range(30)])
    z = z[np.isfinite(z)]
    assert 0.25 < z.min() < 0.6
    assert 7.0 < z.max() < 10.8
    assert 2.2 < np.median(z) < 3.3
    assert 2.5 < z.mean() < 3.6


def test_textures_have_variety_including_dark_patches() -> None:
    rig = make_rig(40)
    kinds, dark = set(), 0
    for s in range(12):
        for p in make_scene(s, rig).prims:
            kinds.add(p.texture.kind)
            dark += p.texture.dark_fraction > 0
    assert {"noise", "stripes", "checker"} <= kinds
    assert dark >= 3
    # dark patches are really dark (low albedo that defeats structured light)
    from dp5k_studio.textures import TextureSpec, evaluate

    u, v = np.meshgrid(np.linspace(0, 30, 300), np.linspace(0, 30, 300))
    alb = evaluate(TextureSpec("noise", dark_fraction=0.3, seed=1), u.ravel(), v.ravel())
    assert 0.2 < (alb.max(axis=1) < 0.04).mean() < 0.35  # dark_fraction 0.3 of the area
