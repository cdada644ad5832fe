"""Structured light: projector pixels land where the true geometry says; shadows are real; Gray code decodes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dp5k_studio import Scene, Studio, make_rig, make_scene
from dp5k_studio.geometry import Quad
from dp5k_studio.textures import TextureSpec


def _slanted_plane() -> tuple[Scene, np.ndarray, np.ndarray]:
    n = np.array([0.35, -0.15, -1.0])
    n /= np.linalg.norm(n)
    p0 = np.array([0.0, 0.0, 2.3])
    u = np.cross([0.0, 1.0, 0.0], n)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    q = Quad(p0 - 20 * u - 20 * v, u, v, (40.0, 40.0), TextureSpec("flat", color_a=(0.6, 0.6, 0.6)), "slanted")
    return Scene("slanted", (q,), p0), p0, n


@pytest.fixture(scope="module")
def slanted_studio() -> tuple[Studio, np.ndarray, np.ndarray]:
    scene, p0, n = _slanted_plane()
    return Studio(scene, make_rig(20), supersample=4), p0, n


@pytest.mark.parametrize("xp,yp", [(960, 600), (700, 480), (1250, 700), (900.0, 750.0)])
def test_projector_pixel_lands_where_geometry_says(slanted_studio, xp: int, yp: int) -> None:
    st, p0, n = slanted_studio
    proj = st.rig.projector
    half = 10
    pattern = np.zeros((proj.height, proj.width), np.float32)
    pattern[int(yp) - half : int(yp) + half + 1, int(xp) - half : int(xp) + half + 1] = 1.0
    st.set_projector_image(None)
    dark = st.radiance(0)[:, :, 1].astype(np.float64)
    st.set_projector_image(pattern)
    lit = st.radiance(0)[:, :, 1].astype(np.float64) - dark
    assert lit.max() > 0.05
    yy, xx = np.mgrid[0 : lit.shape[0], 0 : lit.shape[1]]
    cx, cy = (lit * xx).sum() / lit.sum(), (lit * yy).sum() / lit.sum()
    # truth, computed here independently: projector ray -> plane -> camera
    ray = proj.R.T @ np.linalg.solve(proj.K, np.array([xp, yp, 1.0]))
    C = proj.center_m
    X = C + ray * ((p0 - C) @ n) / (ray @ n)
    gt = st.ground_truth(0)
    Xc = gt["R"] @ X + gt["t"]
    u, v, _ = gt["K"] @ (Xc / Xc[2])
    assert np.hypot(cx - u, cy - v) < 0.5


def test_ground_truth_projector_map_is_consistent(slanted_studio) -> None:
    st, p0, n = slanted_studio
    gt = st.ground_truth(0)
    pxy = gt["proj_xy"]
    y, x = 100, 150
    # back-project the camera pixel to the plane and project into the projector
    ray = gt["R"].T @ np.linalg.solve(gt["K"], np.array([x, y, 1.0]))
    C = -gt["R"].T @ gt["t"]
    X = C + ray * ((p0 - C) @ n) / (ray @ n)
    P = gt["projector"]
    Xp = P["R"] @ X + P["t"]
    uv = (P["K"] @ (Xp / Xp[2]))[:2]
    assert np.allclose(pxy[y, x], uv, atol=1e-6)
    assert gt["depth_m"][y, x] == pytest.approx((gt["R"] @ X + gt["t"])[2], abs=1e-9)


def test_projector_shadows_and_occlusions_are_real() -> None:
    st = Studio(make_scene("boxes"), make_rig(20), supersample=1)
    proj = st.rig.projector
    st.set_projector_image(None)
    dark = st.radiance(0)
    st.set_projector_image(np.full((proj.height, proj.width), 255, np.uint8))
    white = st.radiance(0)
    gt = st.ground_truth(0)
    unlit = np.isnan(gt["proj_xy"][:, :, 0]) & np.isfinite(gt["depth_m"])
    core = cv2.erode(unlit.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert core.mean() > 0.005  # the boxes cast projector shadows the camera sees
    assert np.allclose(white[core], dark[core])
    lit = cv2.erode((~unlit).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert (white[lit][:, 1] > dark[lit][:, 1]).all()


def test_gray_code_decodes_to_the_true_projector_column_at_scale_1_8() -> None:
    st = Studio(make_scene("demo01"), make_rig(20), supersample=2)
    proj = st.rig.projector
    gc = cv2.structured_light.GrayCodePattern.create(proj.width, proj.height)
    _, patterns = gc.generate()
    bits = 8  # the 8 most significant column bits: projector scale 1/8
    gray = []
    for b in range(bits):
        st.set_projector_image(patterns[2 * b])
        pos = st.radiance(0)[:, :, 1]
        st.set_projector_image(patterns[2 * b + 1])
        neg = st.radiance(0)[:, :, 1]
        gray.append(pos > neg)
    binary = np.zeros_like(gray[0], dtype=np.int64)
    prev = np.zeros_like(gray[0])
    for g in gray:
        prev = prev ^ g
        binary = binary * 2 + prev
    gt_x = st.ground_truth(0)["proj_xy"][:, :, 0]
    lit = np.isfinite(gt_x)
    coarse = np.floor(np.rint(gt_x[lit]) / (2 ** (11 - bits))).astype(np.int64)
    # camera pixels straddling a stripe boundary may decode to the neighbour code; nothing decodes farther off
    err = np.abs(binary[lit] - coarse)
    assert (err == 0).mean() > 0.85
    assert (err <= 1).mean() > 0.99
