"""The layered DP renderer against exact thin-lens ray tracing (aperture sampling) at depth edges.

The reference traces, for every pixel and for 400 points of the aperture, the ray from the lens point
through the pixel's point on the focal plane into the scene (exact visibility, so exact partial
occlusion); the left view averages the lens points with x < 0 (their light lands on the left of the disc
behind focus), the right view the others, each carrying half the light (Eq. 2).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dp5k_studio import LensSetting, Scene, make_rig, render_dp
from dp5k_studio.geometry import Quad, Sphere, cast, shade_albedo
from dp5k_studio.render import pixel_rays, view_geometry
from dp5k_studio.textures import TextureSpec


def _scene() -> Scene:
    bg = Quad(np.array([-20.0, -20.0, 4.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), (40.0, 40.0),
              TextureSpec("noise", (0.9, 0.8, 0.7), (0.2, 0.3, 0.4), 0.08, seed=1), "bg")
    fg = Sphere(np.array([0.02, 0.0, 1.2]), 0.08, TextureSpec("noise", (0.95, 0.2, 0.1), (0.1, 0.1, 0.9), 0.03, seed=2), "fg")
    return Scene("occlusion", (bg, fg), np.array([0.0, 0.0, 4.0]))


def _aperture_reference(scene: Scene, cam, f_number: float, focus_m: float, n: int = 400) -> dict[str, np.ndarray]:
    H, W = cam.height, cam.width
    yc, xc = np.meshgrid(np.arange(H, dtype=float), np.arange(W, dtype=float), indexing="ij")
    d, zc = pixel_rays(cam, xc.ravel(), yc.ravel())
    C = cam.center_m
    focal_pts = C[None, :] + d * (focus_m / zc)[:, None]
    radius_m = cam.focal_length_mm / f_number / 2000.0
    i = np.arange(n) + 0.5
    r = np.sqrt(i / n) * radius_m
    th = i * math.pi * (3 - math.sqrt(5))
    acc = {"L": np.zeros((H * W, 3)), "R": np.zeros((H * W, 3))}
    cnt = {"L": 0, "R": 0}
    prims = list(scene.prims)
    for k in range(n):
        a = np.array([r[k] * math.cos(th[k]), r[k] * math.sin(th[k]), 0.0])
        lens_pt = C + cam.R.T @ a
        dd = focal_pts - lens_pt[None, :]
        dd /= np.linalg.norm(dd, axis=1, keepdims=True)
        t, idx = cast(prims, lens_pt, dd)
        X = lens_pt[None, :] + t[:, None] * dd
        alb, nrm = shade_albedo(prims, X, idx)
        nrm[np.einsum("ij,ij->i", nrm, dd) > 0] *= -1
        rad = alb * (scene.ambient + scene.key_light * np.clip(nrm @ scene.light_dir, 0, 1))[:, None]
        side = "L" if a[0] < 0 else "R"
        acc[side] += rad
        cnt[side] += 1
    return {s: (acc[s] / cnt[s] / 2).reshape(H, W, 3) for s in acc}


@pytest.fixture(scope="module")
def setup():
    rig = make_rig(80)  # 84 x 56 px: CoC about 7 px at f/1.8 for these depths
    cam = rig.cameras[0]
    scene = _scene()
    geom = view_geometry(scene, cam, None, (), 1)
    return scene, cam, geom


@pytest.mark.parametrize("focus_m,mean_tol", [(4.0, 0.01), (1.2, 0.02)])
def test_layered_views_match_aperture_sampling(setup, focus_m: float, mean_tol: float) -> None:
    scene, cam, geom = setup
    ref = _aperture_reference(scene, cam, 1.8, focus_m)
    lens = LensSetting(85.0, 1.8, focus_m * 1000.0, cam.pixel_pitch_mm)
    hidden = (geom.hidden_radiance(None), geom.hidden["depth_m"] * 1000.0)
    out = render_dp(geom.radiance(None), geom.depth_m * 1000.0, lens, hidden=hidden)
    plain = render_dp(geom.radiance(None), geom.depth_m * 1000.0, lens)
    inner = (slice(8, -8), slice(8, -8))  # the reference sees past the frame; the renderer mirrors it
    for side, view, view_plain in (("L", out.left, plain.left), ("R", out.right, plain.right)):
        err = np.abs(view - ref[side])[inner]
        assert err.mean() < mean_tol * ref[side][inner].mean()
        # single silhouette pixels may differ (the reference's cone grazes the limb in front of the
        # focal plane; the renderer knows one ray per pixel), nothing more
        assert (err.max(axis=2) > 0.05).mean() < 0.005
        if focus_m == 4.0:  # blurred foreground: the hidden background is what makes the edge right
            assert err.max() < 0.06
            assert np.abs(view_plain - ref[side])[inner].max() > 2.5 * err.max()


def test_a_slanted_surface_shows_no_seams_between_its_depth_bins() -> None:
    """A uniform slanted plane before a dark wall spans many CoC bins; away from its silhouette each view
    must stay exactly uniform (no darker seams where the wall behind could leak between bins)."""
    a, b = np.array([-0.6, -2.0, 0.9]), np.array([-0.05, -2.0, 2.4])  # recedes to the right
    u = (b - a) / np.linalg.norm(b - a)
    slab = Quad(a, u, np.array([0.0, 1.0, 0.0]), (float(np.linalg.norm(b - a)), 4.0),
                TextureSpec("flat", color_a=(0.6, 0.6, 0.6)), "slab")
    wall = Quad(np.array([-20.0, -20.0, 6.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), (40.0, 40.0),
                TextureSpec("flat", color_a=(0.03, 0.03, 0.03)), "wall")
    from dp5k_studio import Studio

    st = Studio(Scene("slab", (wall, slab), np.array([0.0, 0.0, 3.0])), make_rig(20), supersample=1)
    rad = st.radiance(0)[:, :, 1]
    on = st.geometry(0).prim == 1
    dp = st.render_views(0, 1.8, 3.0)
    c = float(np.abs(dp.coc_px[on][:, 1]).max())
    import cv2

    inner = cv2.erode(on.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=int(c / 2) + 3).astype(bool)
    assert inner.sum() > 500 and np.ptp(dp.coc_px[inner][:, 1]) > 5  # many bins inside
    for view in (dp.left, dp.right):
        assert np.abs(2 * view[:, :, 1] - rad)[inner].max() < 0.005 * rad[inner].mean()
