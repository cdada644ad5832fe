"""A DP renderer and dataset writer that share no code with dp5k: data diagnose has not seen.

`dp5k diagnose` must hold for any format-v1 dataset, not only for the studio's. This module makes such data
another way, so tests and ``benchmarks/foreign_sweep.py`` can check diagnose on it:

* **Scenes** (:func:`foreign_scene`): a slanted back wall and 2-4 fronto-parallel cards (rectangles and
  ellipses) with their own textures (value noise, stripes, checkers, blobs), drawn on a canvas padded
  beyond the frame so that blur at the border gathers real scene content.
* **Optics** (:func:`render_views`): a *scatter* renderer without occlusion. Every source pixel spreads its
  light over its own half disc (per-pixel PSF, so per-pixel field effects are exact); pixels are grouped by
  signed CoC on a fine grid (0.05 px near focus, 1.5 % of |CoC| beyond) and each group is convolved with its
  kernel (``cv2.filter2D`` on the group's bounding box). Kernels are the area coverage of the disc's half,
  weighted by a radial profile, supersampled at least 8 x per pixel (more for sub-pixel discs). Away from depth edges this is the thin-lens DP
  model of Eq. 2 exactly; at depth edges it lets light through occluders, which diagnose leaves unscored.
* **Effects** follow ``dp5k_common.effects.EFFECT_NAMES`` with this module's own parameterisations and
  magnitudes (:data:`EFFECT_DEFAULTS`), deliberately not the studio's formulas (e.g. a quadratic rim for
  ``psf_profile`` where the studio's is quartic, a linear L/R gain ramp, a rigid shift for misregistration).
* **Writer** (:func:`write_dataset`): PNGs through OpenCV (BGR on disk), the CoC TIFF through tifffile and
  params.json by hand, not through ``dp5k_common.dataset``.

Units: depth and focal lengths in mm, CoC in output px (Eq. 6 divided by the pitch), signs as in
docs/conventions.md (C > 0 behind focus; there the left view receives the left half of the disc).
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import tifffile

EFFECT_DEFAULTS: dict[str, float] = {
    "lr_gain_imbalance": 0.08,  # left gain 1 + a (1 + 0.5 x_n), right 1 - a (1 + 0.5 x_n)
    "field_varying_psf": 0.25,  # CoC x (1 + a r_n^2); the split line moves by 1.2 a (-x_n) of the disc radius (smoothly)
    "chromatic_defocus": 0.12,  # focal length of red +a mm, blue -a mm
    "disparity_scale": 0.3,  # crosstalk: each view takes this share of the other half's light
    "focus_offset": 0.06,  # the lens focuses at F_rec (1 + a)
    "psf_profile": 1.2,  # radial weight 1 + a (rho/R)^2 (a bright rim)
    "front_back_asymmetry": 1.0,  # behind 1 + a (rho/R)^2, in front 1 + a (1 - (rho/R)^2) and 1 + 0.1 a larger
    "misregistration": 0.004,  # both views shifted by (a W, -a H / 2) px
    "noise": 2.0,  # shot variance x (1 + 1.5 a), read sigma x (1 + 0.5 a)
}
NOMINAL_SHOT_VAR = 2e-5
NOMINAL_READ_SIGMA = 1e-3


@dataclass
class ForeignOptics:
    """One capture's thin lens. Lengths in mm; the pitch is that of the output image."""

    focal_length_mm: float
    f_number: float
    focus_distance_mm: float
    pixel_pitch_mm: float


@dataclass
class ForeignScene:
    """A scene on a canvas ``pad`` px wider than the frame on every side.

    Attributes:
        radiance: (H + 2 pad, W + 2 pad, 3) float64 linear radiance in [0, 1].
        depth_mm: (H + 2 pad, W + 2 pad) float64 z-depth in mm.
        pad: canvas margin in px.
        focus_px: (x, y) focus point in frame px.
    """

    radiance: np.ndarray
    depth_mm: np.ndarray
    pad: int
    focus_px: tuple[int, int]


def _value_noise(rng: np.random.Generator, h: int, w: int, cell: float) -> np.ndarray:
    g = rng.uniform(0, 1, (max(2, int(h / cell) + 2), max(2, int(w / cell) + 2)))
    return cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 1)


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """(h, w, 3) albedo in [0.03, 0.95]: a random mix of noise, stripes, checkers and blobs."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    kind = rng.integers(0, 4)
    if kind == 0:
        t = 0.6 * _value_noise(rng, h, w, rng.uniform(3, 12)) + 0.4 * _value_noise(rng, h, w, rng.uniform(1.2, 3))
    elif kind == 1:
        ang = rng.uniform(0, np.pi)
        period = rng.uniform(3, 10)
        t = 0.5 + 0.5 * np.sign(np.sin(2 * np.pi * (xx * np.cos(ang) + yy * np.sin(ang)) / period))
        t = 0.7 * t + 0.3 * _value_noise(rng, h, w, 4)
    elif kind == 2:
        s = rng.integers(2, 7)
        t = ((xx // s + yy // s) % 2).astype(np.float64)
        t = 0.8 * t + 0.2 * _value_noise(rng, h, w, 6)
    else:
        t = _value_noise(rng, h, w, rng.uniform(6, 16))
        t = (t > 0.5).astype(np.float64) * 0.7 + 0.3 * _value_noise(rng, h, w, 2)
    c0, c1 = rng.uniform(0.03, 0.4, 3), rng.uniform(0.5, 0.95, 3)
    return c0 + (c1 - c0) * t[..., None]


def foreign_scene(rng: np.random.Generator, W: int, H: int, pad: int) -> ForeignScene:
    """A slanted textured wall 2.5-6 m away and 2-4 textured cards at 0.5-2.5 m."""
    h, w = H + 2 * pad, W + 2 * pad
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    z_top, z_bottom = rng.uniform(3000, 6000), rng.uniform(2500, 4500)
    depth = z_top + (z_bottom - z_top) * yy / (h - 1) + rng.uniform(-300, 300) * (xx / (w - 1) - 0.5)
    radiance = _texture(rng, h, w)
    for _ in range(int(rng.integers(2, 5))):
        cw, chh = rng.uniform(0.2, 0.45) * W, rng.uniform(0.25, 0.5) * H
        cx, cy = rng.uniform(pad + 0.1 * W, pad + 0.9 * W), rng.uniform(pad + 0.1 * H, pad + 0.9 * H)
        if rng.uniform() < 0.5:
            inside = (np.abs(xx - cx) < cw / 2) & (np.abs(yy - cy) < chh / 2)
        else:
            inside = ((xx - cx) / (cw / 2)) ** 2 + ((yy - cy) / (chh / 2)) ** 2 < 1
        z = rng.uniform(500, 2500)
        front = inside & (z < depth)
        depth[front] = z
        radiance[front] = _texture(rng, h, w)[front]
    fx, fy = int(rng.integers(W // 4, 3 * W // 4)), int(rng.integers(H // 4, 3 * H // 4))
    return ForeignScene(radiance, depth, pad, (fx, fy))


def coc_px(depth_mm: np.ndarray, o: ForeignOptics, focal_length_mm: float | None = None, focus_mm: float | None = None) -> np.ndarray:
    """Signed CoC diameter (output px) by the thin lens: the sensor sits where ``o`` focuses ``focus_mm``
    (default: the recorded focus distance); a colour channel of another focal length focuses elsewhere.
    ``C = A (v - v_z) / v_z`` with aperture ``A = f / N`` (mm), sensor distance ``v``, and ``v_z`` the image
    distance of depth z; with one focal length this is Eq. 6."""
    f = o.focal_length_mm
    fc = f if focal_length_mm is None else focal_length_mm
    F = o.focus_distance_mm if focus_mm is None else focus_mm
    v = 1.0 / (1.0 / f - 1.0 / F)
    vz = 1.0 / (1.0 / fc - 1.0 / depth_mm)
    return (f / o.f_number) * (v - vz) / vz / o.pixel_pitch_mm


def half_kernel(c: float, profile, split: float = 0.0, ss: int = 8, sampling: str = "box") -> np.ndarray:
    """The left view's PSF (odd square) of a point with signed CoC diameter ``c`` (px), as a share of its light.

    ``profile(q, c)`` is the radial weight at ``q = (rho / R)^2``. The left photodiode sees the part of the
    disc with ``sign(c) u < split R`` (u: x offset from the disc centre): the left half for ``c > 0``, the
    right half for ``c < 0`` (docs/conventions.md); ``split`` > 0 moves the split line so that the left view
    gets more than half (an off-axis pixel). The whole disc sums to 2, so the ideal half sums to 1 and the
    view is ``K * radiance / 2``. The right view's PSF is ``half_kernel(c, profile, -split)[:, ::-1]``.
    ``|c| < 0.05`` px is a point of weight ``1 + 4 split / pi`` (a flat disc's share, to first order).

    ``sampling`` is how the continuous PSF becomes pixel weights: ``"box"`` integrates it over each pixel's
    area (the light of a sharp pixel is a point at its centre, collected by a square photodiode);
    ``"tent"`` splats it bilinearly, which is the same integral for a sharp pixel whose light is a uniform
    square (box source and box photodiode make a tent), as dp5k's base model and studio render. They differ
    for discs of a few px: a 1 px half disc's centroid is -0.10 px boxed and -0.21 px (exact) splatted, and
    a disc under about 1 px blurs nothing boxed (docs/deblur.md, "Why foreign_dp lost"); the default stays
    ``"box"`` because the diagnose tests and matrix were measured with it.
    """
    R = abs(c) / 2
    if R < 0.025:
        return np.full((1, 1), 1.0 + 4 * split / math.pi)
    n = int(math.ceil(R + 0.5))
    k = 2 * n + 1
    ss = max(ss, min(256, int(math.ceil(6 / R))))  # a few samples across even a sub-pixel disc
    ss += ss % 2  # even: no sample on the split line x = 0, so neither half gets it
    u = (np.arange(k * ss) + 0.5) / ss - (n + 0.5)
    X, Y = np.meshgrid(u, u)
    q = (X * X + Y * Y) / (R * R)
    w = np.where(q <= 1, profile(np.minimum(q, 1.0), c), 0.0)
    own = np.sign(c) * X < split * R
    wk = np.where(own, w, 0.0)
    if sampling == "box":
        K = wk.reshape(k, ss, k, ss).sum(axis=(1, 3))
    else:
        px = np.arange(-(n + 1), n + 2, dtype=np.float64)
        T = np.maximum(0.0, 1.0 - np.abs(px[:, None] - u[None, :]))  # (k + 2, k ss) bilinear weights
        K = T @ wk @ T.T
    return 2 * K / w.sum()


def _flat(q: np.ndarray, c: float) -> np.ndarray:
    return np.ones_like(q)


@dataclass
class Planted:
    """Effects with their magnitudes (:data:`EFFECT_DEFAULTS` times a strength)."""

    a: dict[str, float] = field(default_factory=dict)

    @classmethod
    def of(cls, effect: str | dict[str, float] | None, strength: float = 1.0) -> "Planted":
        """``effect`` is a name, ``none``, or several names joined by ``+`` (each at ``strength``), or a mapping
        name -> that effect's own strength (times ``strength``)."""
        if isinstance(effect, dict):
            return cls({name: EFFECT_DEFAULTS[name] * s * strength for name, s in effect.items()})
        names = [] if effect in (None, "none") else effect.split("+")
        return cls({name: EFFECT_DEFAULTS[name] * strength for name in names})

    def get(self, name: str) -> float:
        return self.a.get(name, 0.0)

    def profile(self):
        rim, fba = self.get("psf_profile"), self.get("front_back_asymmetry")

        def prof(q: np.ndarray, c: float) -> np.ndarray:
            w = 1 + rim * q
            if fba:
                w = w * ((1 + fba * q) if c > 0 else (1 + fba * (1 - q)))
            return w

        return prof


@functools.lru_cache(maxsize=8192)
def _view_kernel(c: float, split: float, rim: float, fba: float, sampling: str, side: int) -> np.ndarray:
    """``half_kernel(c, Planted profile of (rim, fba), split)`` for the left view (``side`` 1), hflipped for the
    right (-1); read-only. Cached: CoC nodes sit on a fixed grid (:func:`_group_nodes`), so the pairs of a set
    ask for the same kernels again (on a field-varying PSF set, 23,000 builds made 60 % of its writing time)."""
    k = half_kernel(c, Planted({"psf_profile": rim, "front_back_asymmetry": fba}).profile(), split, sampling=sampling)
    k = k if side > 0 else k[:, ::-1]
    k.flags.writeable = False
    return k


def _group_nodes(c: np.ndarray) -> np.ndarray:
    """Quantise signed CoC (px) onto a grid: 0.05 px steps up to 2 px, then 1.5 % of |c|."""
    a = np.abs(c)
    fine = np.round(a / 0.05) * 0.05
    coarse = 2 * np.exp(np.round(np.log(np.maximum(a, 2) / 2) / np.log(1.015)) * np.log(1.015))
    return np.sign(c) * np.where(a < 2, fine, coarse)


def scatter(image: np.ndarray, c: np.ndarray, kernel_of, split_leak: np.ndarray | None = None,
            band: np.ndarray | None = None) -> np.ndarray:
    """Spread every pixel of ``image`` (h, w, ch) over ``kernel_of(c_node, band)``.

    ``c`` (h, w) is the signed CoC per pixel, ``band`` (h, w) an optional integer key that also selects the
    kernel (a field band). With ``split_leak`` (h, w) the PSF of a pixel is ``(1 - l) K + l hflip(K)``
    with ``l`` its leak (crosstalk). Borders are zero (render on a padded canvas).
    """
    h, w = c.shape
    out = np.zeros_like(image)
    nodes = _group_nodes(c)
    bands = np.zeros(c.shape, np.int64) if band is None else band
    for cn in np.unique(nodes):
        at = nodes == cn
        for bn in np.unique(bands[at]):
            sel = at & (bands == bn)
            ys, xs = np.nonzero(sel)
            K = kernel_of(float(cn), int(bn))
            r = K.shape[0] // 2
            y0, y1 = max(ys.min() - r, 0), min(ys.max() + r + 1, h)
            x0, x1 = max(xs.min() - r, 0), min(xs.max() + r + 1, w)
            src = np.where(sel[y0:y1, x0:x1, None], image[y0:y1, x0:x1], 0.0)
            if split_leak is None:
                parts = [(src, K)]
            else:
                l = split_leak[y0:y1, x0:x1, None]
                parts = [(src * (1 - l), K), (src * l, K[:, ::-1])]
            for s, k in parts:
                # filter2D correlates; flip the kernel to scatter (convolve)
                res = cv2.filter2D(s, -1, np.ascontiguousarray(k[::-1, ::-1]), borderType=cv2.BORDER_CONSTANT)
                out[y0:y1, x0:x1] += res.reshape(s.shape)  # filter2D drops a single channel's axis
    return out


def render_views(scene: ForeignScene, o: ForeignOptics, planted: Planted, sampling: str = "box") -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (H, W, 3) left and right views of the frame, linear, each ``H * radiance / 2`` (Eq. 2).

    The right view is the mirror of the left's process: every PSF flipped horizontally."""
    p = scene.pad
    h, w = scene.depth_mm.shape
    W, H = w - 2 * p, h - 2 * p
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    xn, yn = (xx - p) / (W - 1) * 2 - 1, (yy - p) / (H - 1) * 2 - 1
    r2 = (xn**2 + yn**2) / 2
    F_true = o.focus_distance_mm * (1 + planted.get("focus_offset"))
    ca, fvp = planted.get("chromatic_defocus"), planted.get("field_varying_psf")
    leak = np.full((h, w), planted.get("disparity_scale"))
    # off axis the split line moves (microlens offset): split = 1.2 a (-x_n) of the radius, rendered at 9 field
    # bands (x_n = -1, -0.75, ..., 1) with each pixel's light shared linearly between its two bracketing bands, so
    # that the split (and each view's share of the light, about 1 + 4 split / pi) changes smoothly across the
    # field: a pixel that took its nearest band would make a staircase whose brightness steps of about 10 % at
    # the band edges no lens makes, and which no smooth model of the effect can follow.
    band_t = np.clip((xn + 1) * 4, 0, 8)
    band_lo = np.minimum(np.floor(band_t), 7).astype(np.int64)
    band_w = band_t - band_lo  # the upper band's share of the pixel's light
    split_of = lambda bn: 1.2 * fvp * -(bn / 4 - 1)  # noqa: E731
    rim, fba = planted.get("psf_profile"), planted.get("front_back_asymmetry")

    def kernel_of(cn: float, bn: int, side: int) -> np.ndarray:
        """The left (``side`` 1) or right (-1) view's PSF of CoC node ``cn`` in field band ``bn``."""
        return _view_kernel(cn, side * split_of(bn), rim, fba, sampling, side)

    size_front = 1 + 0.1 * planted.get("front_back_asymmetry")
    f = o.focal_length_mm
    groups = [((0,), f + ca), ((1,), f), ((2,), f - ca)] if ca else [((0, 1, 2), f)]
    left, right = np.zeros((h, w, 3)), np.zeros((h, w, 3))
    for chans, fc in groups:
        c = coc_px(scene.depth_mm, o, fc, F_true)
        c = np.where(c < 0, c * size_front, c) * (1 + fvp * r2)
        img = scene.radiance[..., list(chans)] / 2
        lk = leak if leak.any() else None
        shares = [(img * (1 - band_w[..., None]), band_lo), (img * band_w[..., None], band_lo + 1)] if fvp else [(img, None)]
        for part, bd in shares:
            left[..., list(chans)] += scatter(part, c, lambda cn, bn: kernel_of(cn, bn, 1), lk, bd)
            right[..., list(chans)] += scatter(part, c, lambda cn, bn: kernel_of(cn, bn, -1), lk, bd)
    g = planted.get("lr_gain_imbalance")
    if g:
        ramp = g * (1 + 0.5 * xn)[..., None]
        left, right = left * (1 + ramp), right * (1 - ramp)
    left, right = left[p : p + H, p : p + W], right[p : p + H, p : p + W]
    m = planted.get("misregistration")
    if m:
        A = np.float64([[1, 0, m * W], [0, 1, -m * H / 2]])
        left = cv2.warpAffine(left, A, (W, H), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        right = cv2.warpAffine(right, A, (W, H), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return left, right


def sharp_frame(scene: ForeignScene, o: ForeignOptics, sharp_f_number: float) -> np.ndarray:
    """(H, W, 3) sharp image: the radiance (``sharp_f_number`` 0) or a full-aperture render at that f-number."""
    p = scene.pad
    h, w = scene.depth_mm.shape
    if sharp_f_number == 0:
        s = scene.radiance
    else:
        o22 = ForeignOptics(o.focal_length_mm, sharp_f_number, o.focus_distance_mm, o.pixel_pitch_mm)
        c = coc_px(scene.depth_mm, o22)

        def full(cn: float, bn: int) -> np.ndarray:
            k = half_kernel(cn, _flat)
            return (k + k[:, ::-1]) / 2

        s = scatter(scene.radiance, c, full)
    return s[p : h - p, p : w - p]


def add_noise(rng: np.random.Generator, img: np.ndarray, planted: Planted) -> np.ndarray:
    a = planted.get("noise")
    var = NOMINAL_SHOT_VAR * (1 + 1.5 * a) * np.clip(img, 0, None) + (NOMINAL_READ_SIGMA * (1 + 0.5 * a)) ** 2
    return img + rng.normal(0, 1, img.shape) * np.sqrt(var)


def _png16(path: Path, rgb: np.ndarray) -> None:
    v = np.round(np.clip(rgb, 0, 1) * 65535).astype(np.uint16)
    if not cv2.imwrite(str(path), v[..., ::-1] if v.ndim == 3 else v):
        raise OSError(f"could not write {path}")


def write_dataset(
    out: Path,
    effect: str | dict[str, float] | None,
    strength: float = 1.0,
    *,
    scenes: int = 12,
    size: tuple[int, int] = (192, 128),
    f_numbers: tuple[float, ...] = (2.0, 4.0),
    seed: int = 0,
    sharp_f_number: float | None = 0.0,
    state_sharp_f_number: bool = True,
    focal_length_mm: float = 50.0,
    sensor_width_mm: float = 24.0,
    noise: bool = True,
    sampling: str = "box",
) -> dict[str, list[str]]:
    """Write a format-v1 dataset of ``scenes`` x ``f_numbers`` pairs with ``effect`` planted (:meth:`Planted.of`).

    Splits by scene: the last 2 scenes test, the 2 before val, the rest train. ``sharp_f_number`` is the
    f-number ``sharp`` is rendered at (0 = all-in-focus); with ``state_sharp_f_number`` False params.json
    does not say it. ``noise`` False leaves the views noise-free; ``sampling`` is the PSFs' pixel sampling
    (:func:`half_kernel`). Returns the splits.
    """
    W, H = size
    rng = np.random.default_rng(seed)
    planted = Planted.of(effect, strength)
    pitch = sensor_width_mm / W
    # the canvas margin covers the largest blur any depth (0.5-6 m) can get at any focus (0.5-6 m)
    worst = ForeignOptics(focal_length_mm, min(f_numbers), 6000.0, pitch)
    cmax = max(abs(float(coc_px(np.float64(500), worst))), abs(float(coc_px(np.float64(6000), ForeignOptics(focal_length_mm, min(f_numbers), 500.0, pitch)))))
    pad = int(math.ceil(1.4 * cmax / 2)) + 4
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    for si in range(scenes):
        scene = foreign_scene(rng, W, H, pad)
        fx, fy = scene.focus_px
        F = float(scene.depth_mm[fy + pad, fx + pad])
        p = pad
        depth_frame = np.round(scene.depth_mm[p : p + H, p : p + W])
        split = "test" if si >= scenes - 2 else ("val" if si >= scenes - 4 else "train")
        for N in f_numbers:
            o = ForeignOptics(focal_length_mm, N, F, pitch)
            left, right = render_views(scene, o, planted, sampling)
            if noise:
                left, right = add_noise(rng, left, planted), add_noise(rng, right, planted)
            sharp = sharp_frame(scene, o, sharp_f_number or 0.0)
            coc = coc_px(depth_frame, o).astype(np.float32)
            pid = f"fs{seed}-{si:02d}_c0_f{N:g}"
            d = out / "pairs" / pid
            d.mkdir(parents=True, exist_ok=True)
            _png16(d / "sharp.png", sharp)
            _png16(d / "left.png", left)
            _png16(d / "right.png", right)
            if not cv2.imwrite(str(d / "depth.png"), depth_frame.astype(np.uint16)):
                raise OSError(f"could not write {d / 'depth.png'}")
            tifffile.imwrite(d / "coc.tif", coc)
            params = {
                "pair_id": pid, "scene": f"fs{seed}-{si:02d}", "camera": "c0", "f_number": N,
                "focus_distance_mm": F, "focal_length_mm": focal_length_mm, "pixel_pitch_mm": pitch,
                "focus_point_px": [fx, fy], "image_size": [W, H],
            }
            if state_sharp_f_number:
                params["sharp_f_number"] = float(sharp_f_number or 0.0)
            (d / "params.json").write_text(json.dumps(params, indent=1))
            splits[split].append(pid)
    index = {"format": "dp5k-dataset", "version": 1, "splits": splits, "generator": "dp5k_testing.foreign_dp"}
    (out / "dataset.json").write_text(json.dumps(index, indent=1))
    return splits
