"""Layered scenes for :mod:`dp5k_testing.aperture_dp`: textured planes (fronto-parallel or slanted) with shapes.

Shares no code with dp5k (numpy and OpenCV only). A scene is a back plane that fills the canvas and 2-4
cut-out planes in front of it, each with its own texture:

* **1/f noise** (amplitude spectrum ~ 1/f^b, b in [0.8, 1.2], as natural images), coloured by mixing three
  independent fields;
* **glyphs**: rows of random letters and digits (OpenCV's Hershey fonts) on a smooth background, i.e. printed text;
* **gradients** with a few thin strokes and dots: large smooth regions (where noise can be measured) with sharp detail;
* **mosaic**: flat-coloured cells (nearest of random seeds) with a little 1/f texture, i.e. piecewise-constant patches.

Geometry lives in the frame of the *central* (pinhole) view: a point of a layer is addressed by where its chief
ray meets the sensor, ``p = (x, y)`` in output px (pixel centres at integers, x right, y down). Every layer is a
plane in 3-D, so its inverse depth is affine in ``p`` (``1/z = g0 + gx x + gy y``, z in mm); textures and masks
are sampled on a canvas ``pad`` px beyond the frame on every side at :data:`TEXELS_PER_PX` texels per px, so
that light from outside the frame and sub-pixel detail exist.
"""

from __future__ import annotations

import string
from dataclasses import dataclass

import cv2
import numpy as np

TEXELS_PER_PX = 2
"""Texture samples per output pixel along each axis: detail finer than a pixel, integrated by the renderer."""


@dataclass
class Layer:
    """One plane of a scene.

    Attributes:
        rgba: (Ht, Wt, 4) float32 texture (linear radiance in [0, 1]) and coverage (1 inside the shape, 0 outside),
            on the padded canvas at :data:`TEXELS_PER_PX` texels per px.
        inv_depth: (g0, gx, gy): ``1/z = g0 + gx x + gy y`` in 1/mm at frame px ``(x, y)`` of the central view.
    """

    rgba: np.ndarray
    inv_depth: tuple[float, float, float]

    def inv_depth_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """1/z (1/mm) of the plane at frame px ``(x, y)`` (any broadcastable shapes)."""
        g0, gx, gy = self.inv_depth
        return g0 + gx * x + gy * y


@dataclass
class LayeredScene:
    """A back plane (``layers[0]``, covering the whole canvas) and cut-out planes in front of it.

    Attributes:
        layers: back first; the z-buffer, not the order, decides what is in front.
        size: (W, H) of the frame in output px.
        pad: canvas margin in output px on every side.
        focus_px: (x, y) the focus point in frame px.
    """

    layers: list[Layer]
    size: tuple[int, int]
    pad: int
    focus_px: tuple[int, int]

    def texel_of(self) -> tuple[float, float]:
        """(scale, offset) with texel coordinate = scale * frame px + offset (OpenCV pixel-centre convention): every
        output pixel centre sits on a texel, so an in-focus pixel is its texels' exact area average."""
        s = TEXELS_PER_PX
        return float(s), float(s * self.pad)

    def pinhole_depth_mm(self, margin: int = 0) -> np.ndarray:
        """(H + 2 margin, W + 2 margin) z-depth in mm of the nearest surface at each pixel centre of the central
        view (``margin`` <= pad px beyond the frame on every side)."""
        W, H = self.size
        ys, xs = np.mgrid[-margin : H + margin, -margin : W + margin].astype(np.float64)
        s, off = self.texel_of()
        ti = np.clip(np.round(s * ys + off).astype(np.int64), 0, self.layers[0].rgba.shape[0] - 1)
        tj = np.clip(np.round(s * xs + off).astype(np.int64), 0, self.layers[0].rgba.shape[1] - 1)
        best = self.layers[0].inv_depth_at(xs, ys)
        for layer in self.layers[1:]:
            iz = layer.inv_depth_at(xs, ys)
            cover = (layer.rgba[ti, tj, 3] >= 0.5) & (iz > best)
            best = np.where(cover, iz, best)
        return 1.0 / best


def pink_noise(rng: np.random.Generator, h: int, w: int, exponent: float) -> np.ndarray:
    """(h, w) zero-mean, unit-std noise whose amplitude spectrum falls as 1/f^exponent (f in cycles/texel)."""
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-exponent)
    amp[0, 0] = 0.0
    spec = (rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape)) * amp
    n = np.fft.irfft2(spec, s=(h, w))
    return (n - n.mean()) / (n.std() + 1e-12)


def _colour_mix(rng: np.random.Generator, fields: list[np.ndarray]) -> np.ndarray:
    """(h, w, 3) in [0.04, 0.9]: a random base colour plus each field times a random colour direction."""
    base = rng.uniform(0.25, 0.6, 3)
    img = np.broadcast_to(base, fields[0].shape + (3,)).copy()
    for k, fld in enumerate(fields):
        img += (rng.uniform(-1, 1, 3) * (0.2 if k == 0 else 0.09))[None, None, :] * fld[..., None]
    return np.clip(img, 0.04, 0.9)


def _tex_pink(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    return _colour_mix(rng, [pink_noise(rng, h, w, rng.uniform(0.8, 1.2)) for _ in range(3)])


def _paint(img: np.ndarray, coverage: np.ndarray, colour: np.ndarray) -> None:
    """Blend ``colour`` into ``img`` (h, w, 3) where the 8-bit anti-aliased ``coverage`` (h, w) is drawn."""
    a = coverage.astype(np.float64)[..., None] / 255.0
    img *= 1.0 - a
    img += a * colour


def _tex_glyphs(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    img = _colour_mix(rng, [0.4 * pink_noise(rng, h, w, 1.4)])
    ink = rng.uniform(0.04, 0.3, 3) if img.mean() > 0.35 else rng.uniform(0.6, 0.9, 3)
    chars = list(string.ascii_letters + string.digits + "   ")
    scale = rng.uniform(0.35, 0.8) * TEXELS_PER_PX / 2
    line_h = int(34 * scale) + 4
    font = int(rng.choice([cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX]))
    cover = np.zeros((h, w), np.uint8)
    for y in range(line_h, h + line_h, line_h):
        text = "".join(rng.choice(chars, size=max(4, int(w / (18 * scale)))))
        cv2.putText(cover, text, (int(rng.integers(-10, 5)), y), font, scale, 255, max(1, int(round(2 * scale))), cv2.LINE_AA)
    _paint(img, cover, ink)
    return np.clip(img, 0.04, 0.9)


def _tex_gradient(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    ang = rng.uniform(0, 2 * np.pi)
    ramp = (xx * np.cos(ang) + yy * np.sin(ang)) / max(h, w)
    c0, c1 = rng.uniform(0.1, 0.45, 3), rng.uniform(0.45, 0.85, 3)
    img = c0 + (c1 - c0) * (ramp - ramp.min())[..., None] / (np.ptp(ramp) + 1e-9)
    img += 0.02 * pink_noise(rng, h, w, 1.5)[..., None]
    for _ in range(int(rng.integers(8, 20))):
        cover = np.zeros((h, w), np.uint8)
        p0 = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        if rng.uniform() < 0.6:
            p1 = (p0[0] + int(rng.integers(-w // 3, w // 3)), p0[1] + int(rng.integers(-h // 3, h // 3)))
            cv2.line(cover, p0, p1, 255, int(rng.integers(1, 4)), cv2.LINE_AA)
        else:
            cv2.circle(cover, p0, int(rng.integers(2, 9)), 255, -1, cv2.LINE_AA)
        _paint(img, cover, rng.uniform(0.04, 0.9, 3))
    return np.clip(img, 0.04, 0.9)


def _tex_mosaic(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    seeds = np.ones((h, w), np.uint8)
    n = int(rng.integers(30, 90))
    seeds[rng.integers(0, h, n), rng.integers(0, w, n)] = 0
    _, labels = cv2.distanceTransformWithLabels(seeds, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_CCOMP)
    palette = rng.uniform(0.06, 0.88, (int(labels.max()) + 1, 3))
    img = palette[labels] + 0.05 * pink_noise(rng, h, w, 1.0)[..., None]
    return np.clip(img, 0.04, 0.9)


TEXTURES = (_tex_pink, _tex_glyphs, _tex_gradient, _tex_mosaic)


def _shape_mask(rng: np.random.Generator, h: int, w: int, centre: tuple[float, float], size: tuple[float, float]) -> np.ndarray:
    """(h, w) float32 coverage of a random shape (rotated rectangle, ellipse, convex polygon or a frame with a hole)
    at texel ``centre`` with half-extents ``size`` (texels)."""
    m = np.zeros((h, w), np.uint8)
    cx, cy = centre
    a, b = size
    kind = int(rng.integers(0, 4))
    ang = float(rng.uniform(-35, 35))
    if kind == 0 or kind == 3:
        box = cv2.boxPoints(((cx, cy), (2 * a, 2 * b), ang)).astype(np.int32)
        cv2.fillPoly(m, [box], 1)
        if kind == 3:  # a frame: the rectangle with a hole
            hole = cv2.boxPoints(((cx, cy), (1.1 * a, 1.1 * b), ang)).astype(np.int32)
            cv2.fillPoly(m, [hole], 0)
    elif kind == 1:
        cv2.ellipse(m, (int(cx), int(cy)), (int(a), int(b)), ang, 0, 360, 1, -1)
    else:
        th = np.sort(rng.uniform(0, 2 * np.pi, int(rng.integers(5, 9))))
        pts = np.stack([cx + a * np.cos(th) * rng.uniform(0.7, 1.0, th.size), cy + b * np.sin(th) * rng.uniform(0.7, 1.0, th.size)], 1)
        cv2.fillPoly(m, [cv2.convexHull(pts.astype(np.int32))], 1)
    return m.astype(np.float32)


def _plane(z_mm: float, tilt_x: float, tilt_y: float, cx: float, cy: float, W: int, H: int) -> tuple[float, float, float]:
    """Inverse-depth plane through depth ``z_mm`` at frame px (cx, cy), 1/z changing by ``tilt_x`` (``tilt_y``)
    of its value over the frame width (height)."""
    g = 1.0 / z_mm
    gx, gy = g * tilt_x / W, g * tilt_y / H
    return g - gx * cx - gy * cy, gx, gy


def layered_scene(rng: np.random.Generator, size: tuple[int, int], pad: int) -> LayeredScene:
    """A back plane 2.2-6 m away (slanted: farther at the top, tilted in x) and 2-4 cut-out planes 0.65-1.8 m
    away (half of them slanted by up to +-20 % in 1/z across the frame), each with a random texture."""
    W, H = size
    s = TEXELS_PER_PX
    ht, wt = (H + 2 * pad) * s, (W + 2 * pad) * s
    z_top, z_bottom = rng.uniform(3000, 6000), rng.uniform(2200, 3500)
    g_top, g_bottom = 1 / z_top, 1 / z_bottom
    gy = (g_bottom - g_top) / H
    gx = rng.uniform(-0.15, 0.15) * g_bottom / W
    back_g = (g_top - gx * W / 2, gx, gy)
    layers = [Layer(np.dstack([TEXTURES[int(rng.integers(0, 4))](rng, ht, wt), np.ones((ht, wt))]).astype(np.float32), back_g)]
    for _ in range(int(rng.integers(2, 5))):
        cx, cy = rng.uniform(0.1, 0.9) * W, rng.uniform(0.1, 0.9) * H
        half = (rng.uniform(0.12, 0.3) * W, rng.uniform(0.15, 0.4) * H)
        slant = rng.uniform() < 0.5
        g = _plane(rng.uniform(650, 1800), *(rng.uniform(-0.2, 0.2, 2) if slant else (0.0, 0.0)), cx, cy, W, H)
        tex = TEXTURES[int(rng.integers(0, 4))](rng, ht, wt)
        mask = _shape_mask(rng, ht, wt, (s * (cx + pad), s * (cy + pad)), (s * half[0], s * half[1]))
        layers.append(Layer(np.dstack([tex, mask]).astype(np.float32), g))
    fx, fy = int(rng.integers(W // 4, 3 * W // 4)), int(rng.integers(H // 4, 3 * H // 4))
    return LayeredScene(layers, (W, H), pad, (fx, fy))


def point_scene(size: tuple[int, int], pad: int, at_px: tuple[float, float], z_mm: float, sigma_px: float = 0.7,
                brightness: float = 1.0) -> LayeredScene:
    """A point-like source on a black plane at depth ``z_mm``: a Gaussian spot of ``sigma_px`` (output px) at
    frame px ``at_px``, for tests of the renderer's PSF (a smooth spot, not a cut-out, so its light does not
    depend on where it falls between texels)."""
    W, H = size
    s = TEXELS_PER_PX
    ht, wt = (H + 2 * pad) * s, (W + 2 * pad) * s
    yy, xx = np.mgrid[0:ht, 0:wt].astype(np.float64)
    tx, ty = s * (at_px[0] + pad), s * (at_px[1] + pad)
    spot = brightness * np.exp(-((xx - tx) ** 2 + (yy - ty) ** 2) / (2 * (s * sigma_px) ** 2))
    return LayeredScene([Layer(np.dstack([spot, spot, spot, np.ones((ht, wt))]).astype(np.float32), (1.0 / z_mm, 0.0, 0.0))],
                        (W, H), pad, (int(at_px[0]), int(at_px[1])))


def plane_scene(size: tuple[int, int], pad: int, rgb: np.ndarray | None, z_mm: float, rng: np.random.Generator | None = None) -> LayeredScene:
    """One fronto-parallel plane at ``z_mm`` filling the canvas, with texture ``rgb`` ((Ht, Wt, 3) at texel
    resolution) or a 1/f texture drawn from ``rng``: for tests."""
    W, H = size
    s = TEXELS_PER_PX
    ht, wt = (H + 2 * pad) * s, (W + 2 * pad) * s
    tex = _tex_pink(rng or np.random.default_rng(0), ht, wt) if rgb is None else rgb
    return LayeredScene([Layer(np.dstack([tex, np.ones((ht, wt))]).astype(np.float32), (1.0 / z_mm, 0.0, 0.0))], (W, H), pad,
                        (W // 2, H // 2))


def max_abs_coc_px(scene: LayeredScene, coc_of_inv_depth, margin: int) -> float:
    """Largest |CoC| (px) over the central view's visible surfaces within ``margin`` px of the frame, for a
    CoC that is a function of 1/z (1/mm)."""
    return float(np.max(np.abs(coc_of_inv_depth(1.0 / scene.pinhole_depth_mm(margin)))))


__all__ = ["Layer", "LayeredScene", "TEXELS_PER_PX", "layered_scene", "max_abs_coc_px", "pink_noise", "plane_scene",
           "point_scene"]
