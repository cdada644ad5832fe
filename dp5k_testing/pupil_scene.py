"""Scenes for :mod:`dp5k_testing.pupil_dp`: stacks of textured, cut-out planar layers, ordered back to front.

A scene is what a layered ("over") compositor needs: per layer a pixel-area-integrated colour, a coverage (alpha,
antialiased at 4 x 4 samples per px) and the inverse depth of its plane at every pixel of a canvas ``pad`` px wider
than the frame on each side (so blur at the frame border gathers real scene content). A plane's inverse depth is
affine in the image coordinates, so its CoC (affine in inverse depth) is too.

The generator works in the CoC the widest aperture gives (output px at the recorded focus), then converts to depth:

* a slanted **back plane** behind focus (3-25 px of CoC at 256 px width, never beyond infinity);
* 0-2 layers between it and focus; a **subject** in focus at the focus point (fronto-parallel or slanted through
  focus); an optional receding **floor** crossing focus (from well in front of focus at the bottom to behind it);
  1-2 layers just in front of focus and 1-2 **near** layers (down to -22 px) towards the frame's edges.
* Each new layer lies in front of everything it covers (its CoC is at least 1 px below theirs over its footprint),
  so back-to-front order is depth order, and none covers the focus point.
* Textures are the module's own: 1/f^beta noise mixed into colour by a random matrix, polygon mosaics, text-like
  strokes (letters, lines, arcs) and straight edges, each over a 1/f floor so that every pixel has texture, in
  [0.04, 0.92] linear. They are drawn at 2 x 2 samples per px and box-filtered (pixel-area integration).

Everything in numpy and OpenCV; no dp5k import. Units: depth in mm, positions and CoC in output px.
"""

from __future__ import annotations

import math
import string
from dataclasses import dataclass, field

import cv2
import numpy as np

SUPERSAMPLE_TEXTURE = 2
"""Texture samples per px along each axis (box-filtered to the pixel grid)."""
SUPERSAMPLE_ALPHA = 4
"""Coverage samples per px along each axis for the layers' cut-out edges."""
REFERENCE_WIDTH_PX = 256
"""Scene CoC targets (and shape sizes) are stated for a frame this wide and scale with the width."""


@dataclass
class Layer:
    """One planar layer on the canvas.

    Attributes:
        colour: (Hc, Wc, 3) float32 linear radiance in [0, 1], pixel-area integrated.
        alpha: (Hc, Wc) float32 coverage in [0, 1].
        inv_depth: (Hc, Wc) float64 inverse z-depth (1/mm) of the layer's plane at each canvas pixel centre.
        name: what the generator made it as (``back``, ``subject``, ``floor``, ``mid``, ``near``, ...).
    """

    colour: np.ndarray
    alpha: np.ndarray
    inv_depth: np.ndarray
    name: str = "layer"


@dataclass
class LayerScene:
    """Layers back to front on a canvas of (H + 2 pad, W + 2 pad) px.

    Attributes:
        layers: back to front (each lies in front of whatever it covers).
        size: (W, H) of the frame in px.
        pad: canvas margin in px.
        focus_px: (x, y) frame px of the focus point (on the subject, visible).
        focus_mm: z-depth at the focus point (the recorded focus distance).
    """

    layers: list[Layer]
    size: tuple[int, int]
    pad: int
    focus_px: tuple[int, int] = (0, 0)
    focus_mm: float = 1000.0
    meta: dict = field(default_factory=dict)

    @property
    def canvas_shape(self) -> tuple[int, int]:
        W, H = self.size
        return H + 2 * self.pad, W + 2 * self.pad

    def visible_inv_depth(self, threshold: float = 0.5) -> np.ndarray:
        """(Hc, Wc) inverse depth of the front-most layer whose coverage is >= ``threshold`` (the pinhole's)."""
        out = self.layers[0].inv_depth.copy()
        for layer in self.layers[1:]:
            m = layer.alpha >= threshold
            out[m] = layer.inv_depth[m]
        return out

    def depth_mm(self) -> np.ndarray:
        """(H, W) float64 z-depth of the visible surface in the frame (mm)."""
        p = self.pad
        W, H = self.size
        return 1.0 / self.visible_inv_depth()[p : p + H, p : p + W]

    def radiance(self) -> np.ndarray:
        """(H, W, 3) float32 all-in-focus frame: the layers composited "over" with their coverages, no blur."""
        out = np.zeros(self.layers[0].colour.shape, np.float32)
        for layer in self.layers:
            a = layer.alpha[..., None]
            out = layer.colour * a + (1.0 - a) * out
        p = self.pad
        W, H = self.size
        return out[p : p + H, p : p + W]


# ------------------------------------------------------------------------------------------------ textures
def pink_noise(rng: np.random.Generator, h: int, w: int, beta: float, count: int = 1) -> list[np.ndarray]:
    """``count`` independent (h, w) float64 fields with amplitude spectrum 1 / f^beta (complex Gaussian spectra),
    integrated over pixel areas (the box's sinc in the spectrum), each scaled to [0, 1] over mean +- 2.5 standard
    deviations (clipped)."""
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta) * np.sinc(fx) * np.sinc(fy)
    amp[0, 0] = 0.0
    out: list[np.ndarray] = []
    while len(out) < count:  # a complex field's real and imaginary parts are two independent real fields
        spec = amp * (rng.standard_normal((h, w)) + 1j * rng.standard_normal((h, w)))
        z = np.fft.ifft2(spec)
        for n in (z.real, z.imag)[: count - len(out)]:
            m, sd = n.mean(), n.std()
            out.append(np.clip((n - m) / (5.0 * max(sd, 1e-12)) + 0.5, 0.0, 1.0))
    return out


def _colourise(rng: np.random.Generator, fields: list[np.ndarray]) -> np.ndarray:
    """Mix scalar fields into RGB with a random non-negative matrix (channels differ, so every channel has texture)."""
    m = rng.uniform(0.15, 1.0, (len(fields), 3))
    m /= m.sum(0, keepdims=True)
    stack = np.stack(fields, -1)
    return stack @ m


def _tex_pink(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    return _colourise(rng, pink_noise(rng, h, w, rng.uniform(0.6, 1.1), 3))


def _tex_mosaic(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    img = np.empty((h, w, 3))
    img[:] = rng.uniform(0.1, 0.9, 3)
    scale = max(h, w)
    for _ in range(int(rng.integers(25, 60))):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        r = rng.uniform(0.02, 0.12) * scale
        k = int(rng.integers(3, 7))
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        rr = r * rng.uniform(0.5, 1.0, k)
        pts = np.stack([cx + rr * np.cos(ang), cy + rr * np.sin(ang)], -1)
        cv2.fillPoly(img, [np.round(pts * 16).astype(np.int32)], tuple(float(v) for v in rng.uniform(0.05, 0.95, 3)),
                     lineType=cv2.LINE_AA, shift=4)
    return img


def _tex_strokes(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Text-like strokes: lines of random letters and digits, rules and arcs, on a light or dark ground."""
    dark_on_light = rng.uniform() < 0.6
    ground = rng.uniform(0.55, 0.9, 3) if dark_on_light else rng.uniform(0.05, 0.3, 3)
    ink = rng.uniform(0.03, 0.2, 3) if dark_on_light else rng.uniform(0.6, 0.95, 3)
    m = np.zeros((h, w), np.uint8)  # ink coverage (OpenCV draws text on 8-bit images only)
    chars = string.ascii_letters + string.digits
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX, cv2.FONT_HERSHEY_TRIPLEX,
             cv2.FONT_HERSHEY_PLAIN)
    y = float(rng.uniform(5, 20))
    while y < h + 20:
        scale = rng.uniform(0.35, 1.4) * max(h, w) / 500
        thick = max(1, int(round(scale * rng.uniform(1.0, 2.5))))
        text = "".join(rng.choice(list(chars), int(rng.integers(8, 40))))
        x0 = int(rng.uniform(-30, 20))
        cv2.putText(m, text, (x0, int(y)), fonts[int(rng.integers(len(fonts)))], scale, 255, thick, cv2.LINE_AA)
        y += scale * 30 * rng.uniform(1.1, 1.8)
    for _ in range(int(rng.integers(2, 6))):
        p0 = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        if rng.uniform() < 0.5:
            p1 = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
            cv2.line(m, p0, p1, 255, int(rng.integers(1, 5)), cv2.LINE_AA)
        else:
            ax = (int(rng.uniform(10, w / 2)), int(rng.uniform(10, h / 2)))
            cv2.ellipse(m, p0, ax, float(rng.uniform(0, 180)), 0, float(rng.uniform(90, 360)), 255,
                        int(rng.integers(1, 5)), cv2.LINE_AA)
    cov = (m.astype(np.float64) / 255.0)[..., None]
    return ground * (1.0 - cov) + ink * cov


def _tex_edges(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Straight edges: the plane cut by random lines, each half-plane a colour step."""
    xx = np.arange(w, dtype=np.float32)[None, :]
    yy = np.arange(h, dtype=np.float32)[:, None]
    img = np.empty((h, w, 3), np.float32)
    img[:] = rng.uniform(0.2, 0.7, 3)
    for _ in range(int(rng.integers(6, 14))):
        th = rng.uniform(0, np.pi)
        x0, y0 = np.float32(rng.uniform(0, w)), np.float32(rng.uniform(0, h))
        d = (xx - x0) * np.float32(math.cos(th)) + (yy - y0) * np.float32(math.sin(th))
        img += np.clip(d + 0.5, 0, 1)[..., None] * rng.uniform(-0.25, 0.25, 3).astype(np.float32)
    return img


TEXTURES = (_tex_pink, _tex_mosaic, _tex_strokes, _tex_edges)


def texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """(h, w, 3) float32 texture at pixel resolution, pixel-area integrated, in [0.04, 0.92] with texture everywhere:
    1/f noise alone, or a drawn structure (at 2 x 2 samples per px, box-filtered) over a 1/f floor."""
    s = SUPERSAMPLE_TEXTURE
    kind = int(rng.integers(len(TEXTURES)))
    floor = _tex_pink(rng, h, w)
    if kind == 0:
        img = floor
    else:
        base = cv2.resize(TEXTURES[kind](rng, h * s, w * s).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
        mix = rng.uniform(0.3, 0.5)
        img = (1.0 - mix) * base + mix * floor
    lo, hi = rng.uniform(0.04, 0.15), rng.uniform(0.7, 0.92)
    mn, mx = float(img.min()), float(img.max())
    return (lo + (hi - lo) * (img - mn) / max(mx - mn, 1e-9)).astype(np.float32)


# ------------------------------------------------------------------------------------------------ shapes
def shape_alpha(rng: np.random.Generator, hc: int, wc: int, centre: tuple[float, float], radius: tuple[float, float],
                kind: str | None = None) -> np.ndarray:
    """(hc, wc) float32 coverage of a random cut-out (polygon, ellipse, rounded box, blob or branch) at canvas px."""
    s = SUPERSAMPLE_ALPHA
    m = np.zeros((hc * s, wc * s), np.uint8)
    cx, cy = (centre[0] + 0.5) * s - 0.5, (centre[1] + 0.5) * s - 0.5
    rx, ry = radius[0] * s, radius[1] * s
    kind = kind or str(rng.choice(["polygon", "ellipse", "box", "blob", "branch"]))
    if kind == "polygon":
        k = int(rng.integers(5, 10))
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        rr = rng.uniform(0.6, 1.0, k)
        pts = np.stack([cx + rx * rr * np.cos(ang), cy + ry * rr * np.sin(ang)], -1)
        cv2.fillPoly(m, [np.round(pts).astype(np.int32)], 255)
    elif kind == "ellipse":
        cv2.ellipse(m, (int(cx), int(cy)), (int(rx), int(ry)), float(rng.uniform(0, 180)), 0, 360, 255, -1)
    elif kind == "box":
        t = np.linspace(0, 2 * np.pi, 120, endpoint=False)
        e = 2.0 / rng.uniform(4.0, 10.0)  # a superellipse: a box with rounded corners
        px, py = rx * np.sign(np.cos(t)) * np.abs(np.cos(t)) ** e, ry * np.sign(np.sin(t)) * np.abs(np.sin(t)) ** e
        th = math.radians(rng.uniform(-30, 30))
        pts = np.stack([cx + px * math.cos(th) - py * math.sin(th), cy + px * math.sin(th) + py * math.cos(th)], -1)
        cv2.fillPoly(m, [np.round(pts).astype(np.int32)], 255)
    elif kind == "blob":
        n = pink_noise(rng, hc, wc, 2.2)[0]
        yy, xx = np.mgrid[0:hc, 0:wc].astype(np.float64)
        d = ((xx - centre[0]) / radius[0]) ** 2 + ((yy - centre[1]) / radius[1]) ** 2
        field_ = n - 0.45 * d
        share = min(0.6, math.pi * radius[0] * radius[1] / (hc * wc))  # of the canvas the blob covers
        inside = (field_ > np.percentile(field_, 100 * (1 - share))).astype(np.float32)
        b = cv2.resize(inside, (wc * s, hc * s), interpolation=cv2.INTER_LINEAR)
        m = (b > 0.5).astype(np.uint8) * 255
    else:  # branch: a thick curved stroke with a side shoot
        t = np.linspace(0, 1, 40)
        ang = rng.uniform(0, 2 * np.pi)
        bend = rng.uniform(-0.6, 0.6)
        L = 2.0 * max(rx, ry)
        xs = cx + (t - 0.5) * L * np.cos(ang + bend * t)
        ys = cy + (t - 0.5) * L * np.sin(ang + bend * t)
        width = int(max(3, rng.uniform(0.15, 0.3) * min(rx, ry) * 2))
        cv2.polylines(m, [np.round(np.stack([xs, ys], -1)).astype(np.int32)], False, 255, width)
        j = int(rng.integers(10, 30))
        a2 = ang + rng.choice([-1, 1]) * rng.uniform(0.5, 1.2)
        p1 = (xs[j] + 0.45 * L * math.cos(a2), ys[j] + 0.45 * L * math.sin(a2))
        cv2.line(m, (int(xs[j]), int(ys[j])), (int(p1[0]), int(p1[1])), 255, max(2, int(width * 0.6)))
    return cv2.resize(m.astype(np.float32) / 255.0, (wc, hc), interpolation=cv2.INTER_AREA)


# ------------------------------------------------------------------------------------------------ the generator
def coc_scale_px(focal_length_mm: float, f_number: float, focus_mm: float, pitch_mm: float) -> float:
    """``K``: the CoC (output px, Eq. 6) of a point at infinity: ``c = K (1 - F / d)``, ``1/d = (1 - c/K) / F``."""
    return focal_length_mm**2 / (f_number * (focus_mm - focal_length_mm) * pitch_mm)


def _plane_coc(W: int, H: int, pad: int, c_centre: float, gx: float, gy: float, at: tuple[float, float]) -> np.ndarray:
    """(Hc, Wc) CoC of a plane: ``c_centre`` at frame px ``at``, gradient (gx, gy) px of CoC per px."""
    yy, xx = np.mgrid[0 : H + 2 * pad, 0 : W + 2 * pad].astype(np.float64)
    return c_centre + gx * (xx - pad - at[0]) + gy * (yy - pad - at[1])


def layer_scene(rng: np.random.Generator, size: tuple[int, int], pad: int, focal_length_mm: float, f_number: float,
                pitch_mm: float, focus_range_mm: tuple[float, float] = (700.0, 1200.0)) -> LayerScene:
    """A random scene (module docstring) for a lens of ``focal_length_mm`` at its widest ``f_number``.

    The CoC targets (px at that aperture, recorded focus) scale with ``W / 256``; the recorded focus ``F`` is drawn
    from ``focus_range_mm`` and is the subject's depth at the focus point.
    """
    W, H = size
    s = W / REFERENCE_WIDTH_PX
    hc, wc = H + 2 * pad, W + 2 * pad
    F = float(rng.uniform(*focus_range_mm))
    K = coc_scale_px(focal_length_mm, f_number, F, pitch_mm)
    c_back_max = min(25.0 * s, 0.93 * K)
    c_near_min = -22.0 * s
    margin = 1.0 * s

    def inv_depth(c: np.ndarray) -> np.ndarray:
        return (1.0 - c / K) / F

    layers: list[Layer] = []
    cvis = np.full((hc, wc), np.inf)  # CoC of the visible surface (what a new layer must lie in front of)

    def add(c: np.ndarray, alpha: np.ndarray, name: str, lo: float, hi: float,
            keep_clear: tuple[float, float, float] | None) -> bool:
        """Put a layer in front of what it covers, shifting its CoC nearer if needed; False if it cannot fit."""
        foot = alpha > 0.01
        if foot.sum() < 30:
            return False
        if keep_clear is not None:
            fx, fy, r = keep_clear
            yy, xx = np.ogrid[0:hc, 0:wc]
            if (alpha[((xx - pad - fx) ** 2 + (yy - pad - fy) ** 2) <= r * r] > 0).any():
                return False
        over = float(np.max(c[foot] - (cvis[foot] - margin)))
        if over > 0:
            c = c - over
        inner = foot.copy()
        inner[:pad, :] = inner[-pad:, :] = False
        inner[:, :pad] = inner[:, -pad:] = False
        if not inner.any():
            return False
        cf = c[foot]
        if cf.min() < c_near_min - 2 * s or cf.max() > hi or c[inner].min() < lo:
            return False
        layers.append(Layer(texture(rng, hc, wc), alpha.astype(np.float32), inv_depth(c), name))
        cvis[alpha >= 0.5] = c[alpha >= 0.5]
        return True

    # back plane: behind focus, slanted
    cb = rng.uniform(0.5, 0.88) * c_back_max
    th = rng.uniform(0, 2 * np.pi) if rng.uniform() < 0.4 else rng.choice([-1, 1]) * np.pi / 2 + rng.uniform(-0.4, 0.4)
    span = rng.uniform(0.25, 0.7) * c_back_max
    g = span / math.hypot(W, H)
    cback = _plane_coc(W, H, pad, cb, g * math.cos(th), g * math.sin(th), (W / 2, H / 2))
    lo_b, hi_b = 3.0 * s, c_back_max
    cmin, cmax = cback.min(), cback.max()
    if cmin < lo_b or cmax > hi_b:  # squeeze the plane into [lo_b, hi_b]
        cback = lo_b + (cback - cmin) * min(1.0, (hi_b - lo_b) / max(cmax - cmin, 1e-9))
    cback = np.minimum(cback, hi_b)
    layers.append(Layer(texture(rng, hc, wc), np.ones((hc, wc), np.float32), inv_depth(cback), "back"))
    cvis[:] = cback

    def draw_shape(centre_frac: tuple[tuple[float, float], tuple[float, float]], size_frac: tuple[float, float],
                   kind: str | None = None) -> tuple[np.ndarray, tuple[float, float]]:
        (x0, x1), (y0, y1) = centre_frac
        cx, cy = rng.uniform(x0, x1) * W, rng.uniform(y0, y1) * H
        r = rng.uniform(*size_frac) * W / 2
        rr = (r * rng.uniform(0.7, 1.3), r * rng.uniform(0.5, 1.0))
        return shape_alpha(rng, hc, wc, (cx + pad, cy + pad), rr, kind), (cx, cy)

    # 0-2 layers between the back plane and focus
    for _ in range(int(rng.integers(0, 3))):
        for _try in range(4):
            alpha, at = draw_shape(((0.1, 0.9), (0.1, 0.9)), (0.2, 0.4))
            c0 = rng.uniform(0.2, 0.55) * c_back_max
            gx, gy = rng.uniform(-0.04, 0.04, 2) * s
            if add(_plane_coc(W, H, pad, c0, gx, gy, at), alpha, "mid-behind", 1.5 * s, c_back_max, None):
                break

    # the subject, in focus at the focus point
    subject_ok = False
    for _try in range(8):
        kind = str(rng.choice(["polygon", "ellipse", "box", "blob"]))
        alpha, at = draw_shape(((0.3, 0.7), (0.3, 0.7)), (0.22, 0.38), kind)
        fx, fy = int(round(at[0])), int(round(at[1]))
        core = cv2.erode((alpha >= 0.999).astype(np.uint8), np.ones((13, 13), np.uint8))
        if not core[fy + pad, fx + pad]:
            ys, xs = np.nonzero(core[pad : pad + H, pad : pad + W])
            if xs.size == 0:
                continue
            i = int(np.argmin((xs - fx) ** 2 + (ys - fy) ** 2))
            fx, fy = int(xs[i]), int(ys[i])
        slant = rng.uniform() < 0.5
        gx, gy = (rng.uniform(-0.05, 0.05, 2) * s) if slant else (0.0, 0.0)
        csub = _plane_coc(W, H, pad, 0.0, gx, gy, (fx, fy))
        foot = alpha > 0.01
        if np.max(csub[foot] - (cvis[foot] - margin)) > 0:
            continue  # the subject must not be shifted: it defines the focus
        layers.append(Layer(texture(rng, hc, wc), alpha.astype(np.float32), inv_depth(csub), "subject"))
        cvis[alpha >= 0.5] = csub[alpha >= 0.5]
        subject_ok = True
        break
    if not subject_ok:  # a fronto-parallel card in the middle, always in front of the back plane
        fx, fy = W // 2, H // 2
        alpha = shape_alpha(rng, hc, wc, (fx + pad, fy + pad), (0.25 * W, 0.3 * H), "ellipse")
        csub = np.zeros((hc, wc))
        layers.append(Layer(texture(rng, hc, wc), alpha.astype(np.float32), inv_depth(csub), "subject"))
        cvis[alpha >= 0.5] = 0.0
    clear = (float(fx), float(fy), 14.0 * s)

    # a receding floor through focus, below the focus point
    if rng.uniform() < 0.5:
        top = fy + rng.uniform(16, 40) * s
        if top < H - 10 * s:
            yy, xx = np.mgrid[0:hc, 0:wc].astype(np.float64)
            edge = top + pad + rng.uniform(-0.08, 0.08) * (xx - pad - W / 2) + 3 * s * np.sin(xx / rng.uniform(15, 40))
            alpha = np.clip(yy - edge + 0.5, 0, 1).astype(np.float32)
            c_top = rng.uniform(2, 9) * s
            gy = -(c_top + rng.uniform(8, 16) * s) / max(H - top, 1)
            add(_plane_coc(W, H, pad, c_top, rng.uniform(-0.02, 0.02) * s, gy, (W / 2, top)), alpha, "floor",
                c_near_min, c_back_max, clear)

    # 1-2 layers just in front of focus
    for _ in range(int(rng.integers(1, 3))):
        for _try in range(4):
            alpha, at = draw_shape(((0.05, 0.95), (0.05, 0.95)), (0.15, 0.32))
            c0 = -rng.uniform(2.0, 9.0) * s
            gx, gy = rng.uniform(-0.05, 0.05, 2) * s
            if add(_plane_coc(W, H, pad, c0, gx, gy, at), alpha, "mid-front", c_near_min, 0.0, clear):
                break

    # 1-2 near layers towards the frame's edges
    for _ in range(int(rng.integers(1, 3))):
        for _try in range(6):
            side = rng.uniform()
            cx_rng = (-0.05, 0.25) if side < 0.5 else (0.75, 1.05)
            alpha, at = draw_shape((cx_rng, (0.0, 1.0)), (0.25, 0.5))
            c0 = -rng.uniform(9.0, 20.0) * s
            gx, gy = rng.uniform(-0.04, 0.04, 2) * s
            if add(_plane_coc(W, H, pad, c0, gx, gy, at), alpha, "near", c_near_min, 0.0, clear):
                break

    return LayerScene(layers, (W, H), pad, (fx, fy), 1.0 / float(layers_inv_depth_at(layers, pad, fx, fy)),
                      {"coc_scale_px": K, "f_number": f_number})


def layers_inv_depth_at(layers: list[Layer], pad: int, x: int, y: int) -> float:
    """Inverse depth of the front-most layer covering frame px (x, y) (coverage >= 0.5)."""
    v = layers[0].inv_depth[y + pad, x + pad]
    for layer in layers[1:]:
        if layer.alpha[y + pad, x + pad] >= 0.5:
            v = layer.inv_depth[y + pad, x + pad]
    return float(v)


def plane_scene(size: tuple[int, int], pad: int, colour: np.ndarray, inv_depth: float | np.ndarray) -> LayerScene:
    """One opaque layer over the whole canvas: ``colour`` (Hc, Wc, 3) at ``inv_depth`` (1/mm, scalar or per px)."""
    W, H = size
    hc, wc = H + 2 * pad, W + 2 * pad
    inv = np.broadcast_to(np.asarray(inv_depth, np.float64), (hc, wc)).copy()
    layer = Layer(np.ascontiguousarray(colour, np.float32), np.ones((hc, wc), np.float32), inv, "plane")
    return LayerScene([layer], (W, H), pad, (W // 2, H // 2), float(1.0 / inv[pad + H // 2, pad + W // 2]))


def points_scene(size: tuple[int, int], pad: int, points_px: list[tuple[int, int]], inv_depth: float,
                 value: float = 1.0, background: float = 0.0) -> LayerScene:
    """Point sources (one pixel of ``value`` each, at frame px ``points_px``) on a plane at ``inv_depth`` (1/mm) over
    a uniform ``background``: each view then shows its kernel at every point."""
    W, H = size
    hc, wc = H + 2 * pad, W + 2 * pad
    colour = np.full((hc, wc, 3), background, np.float32)
    for x, y in points_px:
        colour[y + pad, x + pad] = value
    return plane_scene(size, pad, colour, inv_depth)
