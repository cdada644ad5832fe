"""A second independent DP renderer: a light-field *gather* over sub-aperture samples with z-buffer occlusion.

`dp5k diagnose` must name the effects that an outside renderer plants; a result that holds on one renderer only
is an artefact of that renderer. :mod:`dp5k_testing.foreign_dp` scatters every pixel's half disc without
occlusion; this module discretises the other way round and shares no code with it or with dp5k (numpy,
OpenCV, tifffile and json only):

* **Scenes** (:mod:`dp5k_testing.aperture_scene`): a slanted back plane and 2-4 cut-out planes (slanted or
  fronto-parallel) with 1/f, text, gradient and mosaic textures, given at 2 texels per output px.
* **Optics** (:func:`render_views`): the thin lens, sampled at points ``u = (u, v)`` of the lens aperture (unit
  disc in aperture radii; a mirror-symmetric sunflower set, 32-640 points by the pair's largest blur). A ray
  through lens point ``u`` from a scene point whose chief ray meets the sensor at ``p`` (output px) lands at
  ``p - u (c(p) + sa (|u|^2 - 3/5)) / 2``, with ``c`` the signed CoC diameter (Eq. 6 in output px; > 0 behind
  focus) and ``sa`` the spherical aberration (0 for an ideal lens). Each sample renders the pinhole view
  through its lens point: every plane is one affine warp (``cv2.warpAffine``; a plane's 1/z, hence its CoC, is
  affine in ``p``) and a **z-buffer** along each ray keeps the nearest surface, so occlusion at depth edges is
  physical (a near plane hides a far one differently in each sub-aperture view). Pixels integrate over their
  area (each plane's texture is box-filtered over one pixel before the warps), and each sample stands for
  its share of the aperture (a Gaussian footprint of half the samples' spacing on the sensor, so a few
  hundred samples tile a 20 px disc without gaps; the rendering error is ~0.02 of the nominal noise variance).
* **Dual pixel**: the microlens images the exit pupil inverted onto the photodiode pair, so the **left**
  photodiode collects the rays through the lens half ``u > 0``. Behind focus (c > 0) those land on the left
  of the blur disc: the left view gets the left half of the disc (docs/conventions.md), in front of focus the
  right half. The two photodiodes share every ray's light (weights summing to 1), so ``L + R`` is the full
  aperture's blur and each view is half of ``sharp`` where in focus.
* **Effects** follow ``dp5k_common.effects.EFFECT_NAMES`` with this module's own physics and magnitudes
  (:data:`EFFECT_DEFAULTS`, one number per effect, times a strength).
* **Sensor**: shot + read noise on every channel of both views and of ``sharp``, nominally
  :data:`NOMINAL_SHOT_VAR` and :data:`NOMINAL_READ_SIGMA` (``dp5k diagnose --nominal-noise 2e-4,2e-3``).
* **Writer** (:func:`write_dataset`): format v1 by hand (OpenCV PNGs, tifffile, json), ``sharp`` at f/22
  (``sharp_f_number`` 22), splits by scene, and ``planted.json`` at the root for benchmarks (what was
  planted; diagnose never reads it).

Units: depth and lengths in mm, CoC and positions in output px, pupil coordinates in aperture radii.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import cv2
import numpy as np
import tifffile

from .aperture_scene import TEXELS_PER_PX, LayeredScene, layered_scene, max_abs_coc_px

EFFECT_DEFAULTS: dict[str, float] = {
    # each view's angular response tilts with the field: L gain 1 + a s, R gain 1 - a s, s = 0.6 + 0.8 y_n + 0.4 x_n^2
    "lr_gain_imbalance": 0.06,
    # cat's-eye vignetting: a second stop (radius 1 aperture radius) centred at a * the field vector (half-diagonal = 1)
    # clips the pupil off axis; the camera's per-view shading correction then restores each view's brightness
    # (not its PSF)
    "field_varying_psf": 0.6,
    # longitudinal colour: focal length of red f (1 + a), blue f (1 - 1.3 a); the sensor is where green focuses
    "chromatic_defocus": 0.003,
    # a soft split: the left photodiode's share of a ray through pupil x u is Phi(u / a) (a normal CDF)
    "disparity_scale": 0.6,
    # the lens focuses elsewhere: 1 / F_true = 1 / F_recorded - a (a in dioptres, 1/m)
    "focus_offset": 0.08,
    # aperture transmission 1 + a exp(-((rho - 0.85) / 0.12)^2): a bright ring near the rim ("soap bubble")
    "psf_profile": 4.0,
    # spherical aberration: the zone at pupil radius rho lands as if its CoC were c - a (1.8 / N)^3 (rho^2 - 3/5) mm
    # on the sensor (over-corrected: rim-heavy discs behind focus, larger centre-heavy ones in front; the 3/5 keeps
    # zero DP disparity at the focus distance, where the camera's DP autofocus put it)
    "front_back_asymmetry": 0.3,
    # both views against sharp: shifted by (0.6 a, -0.35 a) px and rotated by 0.08 a degrees about the frame centre
    "misregistration": 1.0,
    # the views' noise: shot variance x (1 + a), read sigma x (1 + a / 2)
    "noise": 2.0,
}
NOMINAL_SHOT_VAR = 2e-4
"""Nominal shot-noise variance per unit linear intensity (each view, each channel)."""
NOMINAL_READ_SIGMA = 2e-3
"""Nominal read-noise standard deviation (linear units)."""

SA_REFERENCE_F_NUMBER = 1.8
"""front_back_asymmetry's magnitude is stated at this f-number; third-order spherical aberration scales as 1/N^3."""
VIGNETTING_EDGE = 0.04
"""Width of the second stop's soft edge, in aperture radii (keeps the per-pixel clip free of sampling steps)."""


@dataclass(frozen=True)
class Lens:
    """One capture's thin lens.

    Attributes:
        focal_length_mm: thin-lens focal length (the green channel's).
        f_number: aperture f-number; the aperture diameter is ``focal_length_mm / f_number``.
        focus_distance_mm: the focus distance the camera recorded (params.json).
        pixel_pitch_mm: pitch of the output image on the sensor.
    """

    focal_length_mm: float
    f_number: float
    focus_distance_mm: float
    pixel_pitch_mm: float

    def coc_coefficients(self, focus_mm: float | None = None, channel_focal_length_mm: float | None = None) -> tuple[float, float]:
        """(c0, c1): the signed CoC diameter in output px of a point at inverse depth ``g`` (1/mm) is ``c0 + c1 g``.

        The sensor sits where the green focal length images ``focus_mm`` (default: the recorded distance),
        ``v = f F / (F - f)``; a channel with focal length ``f_c`` images depth z at ``1/v_z = 1/f_c - 1/z``, and
        its CoC is the aperture ``A = f / N`` times ``(v - v_z) / v_z``, i.e. ``A v / f_c - A - A v g``. With
        ``f_c = f`` this is Eq. 6.
        """
        f = self.focal_length_mm
        F = self.focus_distance_mm if focus_mm is None else focus_mm
        fc = f if channel_focal_length_mm is None else channel_focal_length_mm
        A = f / self.f_number
        v = f * F / (F - f)
        return (A * v / fc - A) / self.pixel_pitch_mm, -A * v / self.pixel_pitch_mm

    def coc_px(self, depth_mm: np.ndarray) -> np.ndarray:
        """Eq. 6 at the recorded focus: ``f^2 (d - F) / (N d (F - f))`` / pitch, output px (> 0 behind focus)."""
        c0, c1 = self.coc_coefficients()
        return c0 + c1 / depth_mm


@dataclass
class Effects:
    """Planted effects with their magnitudes (:data:`EFFECT_DEFAULTS` times a strength)."""

    a: dict[str, float]

    @classmethod
    def of(cls, spec: str | Sequence[str] | Mapping[str, float] | None, strength: float = 1.0) -> "Effects":
        """``spec``: ``None``/``"none"``, names joined by ``+`` or a list of names (each at its default times
        ``strength``), or a mapping name -> its own strength (times ``strength``)."""
        if isinstance(spec, Mapping):
            per = {k: float(v) for k, v in spec.items()}
        else:
            names = [] if spec in (None, "none", "") else (spec.split("+") if isinstance(spec, str) else list(spec))
            per = {n: 1.0 for n in names}
        unknown = [n for n in per if n not in EFFECT_DEFAULTS]
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; known: {', '.join(EFFECT_DEFAULTS)}")
        mags = {n: EFFECT_DEFAULTS[n] * s * strength for n, s in per.items()}
        return cls(mags)

    def get(self, name: str) -> float:
        return self.a.get(name, 0.0)


@dataclass
class ApertureSamples:
    """Lens-plane sample points, mirror-symmetric about ``u = 0``.

    Attributes:
        u, v: (n,) lens-plane coordinates in aperture radii (the unit disc); x right, y down. The second half of
            the arrays is the first mirrored (``u -> -u``), so an ideal lens's right PSF is exactly the
            horizontal flip of its left PSF (Eq. 2).
    """

    u: np.ndarray
    v: np.ndarray

    @property
    def rho2(self) -> np.ndarray:
        return self.u * self.u + self.v * self.v

    @property
    def n_half(self) -> int:
        return max(1, self.u.size // 2)


def aperture_samples(n_half: int, rng: np.random.Generator) -> ApertureSamples:
    """``2 n_half`` samples: a sunflower (golden-angle) spiral over the half disc ``u > 0`` with a random twist,
    then its mirror image. Each stands for an equal area of the aperture."""
    i = np.arange(n_half, dtype=np.float64)
    rho = np.sqrt((i + 0.5) / n_half)
    phi = (math.sqrt(5.0) - 1.0) / 2.0
    theta = np.pi * (((i * phi) + rng.uniform()) % 1.0) - np.pi / 2.0
    u, v = rho * np.cos(theta), rho * np.sin(theta)
    return ApertureSamples(np.concatenate([u, -u]), np.concatenate([v, v]))


def sample_spacing_px(coc_px: float, n_half: int) -> float:
    """Distance (px) between neighbouring samples' landing points for a blur of diameter ``coc_px``: the half disc
    (area ``pi c^2 / 8`` px^2) shared by ``n_half`` samples."""
    return math.sqrt(math.pi * coc_px * coc_px / 8.0 / n_half)


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.vectorize(math.erf)(x / math.sqrt(2.0)))


def left_share(samples: ApertureSamples, effects: Effects) -> np.ndarray:
    """(n,) share of each ray's light the left photodiode takes: 1 for ``u > 0``, 0 for ``u < 0`` (ideal split),
    or ``Phi(u / softness)`` with a soft split (``disparity_scale``)."""
    soft = effects.get("disparity_scale")
    if soft > 0:
        return _normal_cdf(samples.u / soft)
    return (samples.u > 0).astype(np.float64)


def transmission(samples: ApertureSamples, effects: Effects) -> np.ndarray:
    """(n,) aperture transmission at each sample (``psf_profile``: a bright ring near the rim), normalised to sum 1."""
    t = np.ones_like(samples.u)
    a = effects.get("psf_profile")
    if a:
        t = t + a * np.exp(-(((np.sqrt(samples.rho2) - 0.85) / 0.12) ** 2))
    return t / t.sum()


def misregistration_matrix(effects: Effects, size: tuple[int, int]) -> np.ndarray:
    """3 x 3 affine taking ideal-frame px to the DP frame's px: rotation by 0.08 a degrees about the frame
    centre, then a shift of (0.6 a, -0.35 a) px (identity without ``misregistration``)."""
    a = effects.get("misregistration")
    W, H = size
    th = math.radians(0.08 * a)
    c, s = math.cos(th), math.sin(th)
    cx, cy = (W - 1) / 2.0, (H - 1) / 2.0
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    to_c = np.array([[1.0, 0.0, -cx], [0.0, 1.0, -cy], [0.0, 0.0, 1.0]])
    back = np.array([[1.0, 0.0, cx + 0.6 * a], [0.0, 1.0, cy - 0.35 * a], [0.0, 0.0, 1.0]])
    return back @ R @ to_c


def field_coordinates(size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) float32 x_n, y_n in [-1, 1] across the frame's width and height."""
    W, H = size
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    return x / max(W - 1, 1) * 2 - 1, y / max(H - 1, 1) * 2 - 1


def lr_gain_field(effects: Effects, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """(H, W) gains of the left and right views for ``lr_gain_imbalance`` (None without it)."""
    a = effects.get("lr_gain_imbalance")
    if not a:
        return None
    xn, yn = field_coordinates(size)
    s = 0.6 + 0.8 * yn + 0.4 * xn * xn
    return 1 + a * s, 1 - a * s


class _CatsEye:
    """Per-pixel pass weight of each lens sample through a second stop (``field_varying_psf``): a disc of radius
    ``1 + VIGNETTING_EDGE`` (aperture radii; its soft edge lies outside the aperture, so on axis it clips nothing)
    centred at ``kappa`` times the field vector (frame half-diagonal = 1)."""

    def __init__(self, kappa: float, size: tuple[int, int]) -> None:
        W, H = size
        y, x = np.mgrid[0:H, 0:W].astype(np.float32)
        half_diag = 0.5 * math.hypot(W - 1, H - 1)
        self.cx = kappa * (x - (W - 1) / 2) / half_diag
        self.cy = kappa * (y - (H - 1) / 2) / half_diag

    def weight(self, u: float, v: float) -> np.ndarray:
        d = np.sqrt((u - self.cx) ** 2 + (v - self.cy) ** 2)
        return np.clip((1.0 + VIGNETTING_EDGE - d) / VIGNETTING_EDGE, 0.0, 1.0)


def _channel_groups(lens: Lens, effects: Effects, focus_mm: float) -> list[tuple[slice, float, float]]:
    """[(channel slice, c0, c1)]: one group for all three channels, or one per channel with longitudinal colour."""
    a = effects.get("chromatic_defocus")
    f = lens.focal_length_mm
    if not a:
        return [(slice(0, 3), *lens.coc_coefficients(focus_mm))]
    return [(slice(k, k + 1), *lens.coc_coefficients(focus_mm, f * (1 + m * a))) for k, m in enumerate((1.0, 0.0, -1.3))]


def true_focus_mm(lens: Lens, effects: Effects) -> float:
    """Where the lens really focuses (mm): ``1 / F_true = 1 / F_recorded - a`` dioptres with ``focus_offset``."""
    d = effects.get("focus_offset")
    if not d:
        return lens.focus_distance_mm
    inv = 1.0 / lens.focus_distance_mm - d / 1000.0
    if inv <= 1.0 / (50.0 * 1000.0):
        raise ValueError(f"focus_offset {d} D moves a {lens.focus_distance_mm:.0f} mm focus beyond 50 m")
    return 1.0 / inv


SA_FOCUS_RHO2 = 3.0 / 5.0
"""The pupil zone (rho^2) that lands where the paraxial focus would: 3/5 is the value at which a uniform half
disc's centroid, hence the DP disparity, is unchanged by the aberration (``<rho^2 u> / <u>`` over the half disc),
i.e. the focus a DP autofocus finds."""


def spherical_aberration_px(lens: Lens, effects: Effects) -> float:
    """``sa`` (output px): the marginal zone's CoC shift, ``-a (1.8 / N)^3`` mm on the sensor; a ray through pupil
    radius rho lands with CoC ``c + sa (rho^2 - 3/5)``."""
    a = effects.get("front_back_asymmetry")
    return -a * (SA_REFERENCE_F_NUMBER / lens.f_number) ** 3 / lens.pixel_pitch_mm


INTERPOLATION_VARIANCE_PX2 = 1.0 / 24.0
"""Bilinear reading at a sub-texel shift ``d`` (texels) smooths by a variance ``d (1 - d)`` texel^2 per axis and keeps
centroids exact; over the many shifts of a defocused point that is 1/6 texel^2 = 1/24 px^2 on average, so defocused
light is ~0.2 px (sigma) softer than in-focus light, which sits on texels."""

FOOTPRINT = 0.5
"""Each sample's footprint: a Gaussian of this many sample spacings (sigma), so that the samples' landing points
tile the blur disc without gaps (a sunflower's lattice frequency is damped ~ exp(-2 pi^2 0.5^2) = 0.7 %)."""


def pixel_area_filter(tex: np.ndarray, sigma_px: float = 0.0) -> np.ndarray:
    """``tex`` (texels, :data:`TEXELS_PER_PX` per px) integrated over an output pixel's area and, with ``sigma_px``,
    blurred by a sample footprint. The texture is read with bilinear (tent) interpolation, and a pixel centre sits on
    a texel: the tent interpolant integrated over the pixel (two texels wide) is the kernel [1/4, 1/2, 1/4]."""
    k = np.float32([0.25, 0.5, 0.25])
    out = cv2.sepFilter2D(tex, -1, k, k, borderType=cv2.BORDER_REFLECT)
    if sigma_px > 0.05:
        out = cv2.GaussianBlur(out, (0, 0), sigma_px * TEXELS_PER_PX, borderType=cv2.BORDER_REFLECT)
    return out.reshape(tex.shape)


class _Compositor:
    """Renders the pinhole view through one lens point for one channel group: a warp per layer and a z-buffer.

    Each layer's colour is integrated over the pixel's area and blurred by its samples' footprint (from the
    layer's median |CoC| and ``n_half``); its coverage stays sharp (the z-buffer keeps crisp occlusion edges)."""

    def __init__(self, scene: LayeredScene, chans: slice, c0: float, c1: float, to_dp: np.ndarray, n_half: int) -> None:
        self.scene = scene
        self.c0, self.c1 = c0, c1
        self.textures = []
        for layer in scene.layers:
            c_med = float(np.median(np.abs(c0 + c1 * layer_inv_depths(scene, layer))))
            sigma = FOOTPRINT * sample_spacing_px(c_med, n_half) if n_half > 1 else 0.0
            col = pixel_area_filter(np.ascontiguousarray(layer.rgba[..., chans]), sigma)
            self.textures.append(np.ascontiguousarray(np.dstack([col.reshape(col.shape[:2] + (-1,)), layer.rgba[..., 3:4]])))
        self.nc = self.textures[0].shape[2] - 1
        W, H = scene.size
        y, x = np.mgrid[0:H, 0:W].astype(np.float32)
        self.x, self.y = x, y
        self.from_dp = np.linalg.inv(to_dp)
        s, off = scene.texel_of()
        self.to_texel = np.array([[s, 0.0, off], [0.0, s, off], [0.0, 0.0, 1.0]])

    def render(self, u: float, v: float, sa_rho2: float) -> np.ndarray:
        """(H, W, nc) float32: the radiance reaching each output pixel through lens point ``(u, v)``;
        ``sa_rho2`` is the spherical aberration's CoC shift at this pupil radius (px).

        The z-buffer keeps, per pixel, the nearest layer whose warped coverage is at least 1/2; the masks and the
        masked copies are OpenCV's (comparisons and copies only, so the result is the same to the bit as with
        numpy's, at a fraction of the cost)."""
        W, H = self.scene.size
        Bs = np.empty((len(self.scene.layers), 3, 3))
        for j, layer in enumerate(self.scene.layers):
            g0, gx, gy = layer.inv_depth
            alpha, bx, by = self.c0 + self.c1 * g0 + sa_rho2, self.c1 * gx, self.c1 * gy
            # landing point r = p - u (alpha + b.p) / 2 = B p, affine in the chief-ray point p
            Bs[j] = ((1.0 - 0.5 * u * bx, -0.5 * u * by, -0.5 * u * alpha),
                     (-0.5 * v * bx, 1.0 - 0.5 * v * by, -0.5 * v * alpha),
                     (0.0, 0.0, 1.0))
        Ps = np.linalg.inv(Bs)  # per layer: the chief-ray point p on its plane of each landing point
        col = zbest = None
        for layer, tex, Binv in zip(self.scene.layers, self.textures, Ps):
            g0, gx, gy = layer.inv_depth
            P = Binv @ self.from_dp  # output px -> chief-ray point p on this plane
            M = self.to_texel @ P
            img = cv2.warpAffine(tex, M[:2], (W, H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                 borderMode=cv2.BORDER_REPLICATE)
            k0 = g0 + gx * P[0, 2] + gy * P[1, 2]
            iz = np.float32(k0) + np.float32(gx * P[0, 0] + gy * P[1, 0]) * self.x + np.float32(gx * P[0, 1] + gy * P[1, 1]) * self.y
            if col is None:
                col, zbest = img, iz
            else:
                cover = cv2.bitwise_and(cv2.compare(cv2.extractChannel(img, self.nc), 0.5, cv2.CMP_GE), cv2.compare(iz, zbest, cv2.CMP_GT))
                cv2.copyTo(img, cover, col)
                cv2.copyTo(iz, cover, zbest)
        return col[..., : self.nc]


def layer_inv_depths(scene: LayeredScene, layer, step: int = 4) -> np.ndarray:
    """1/z (1/mm) of ``layer`` at every ``step``-th px of the canvas where it is present (its whole plane if its
    shape is too small to be hit)."""
    W, H = scene.size
    p = scene.pad
    ys, xs = np.mgrid[-p : H + p : step, -p : W + p : step].astype(np.float64)
    s, off = scene.texel_of()
    ti = np.clip(np.round(s * ys + off).astype(np.int64), 0, layer.rgba.shape[0] - 1)
    tj = np.clip(np.round(s * xs + off).astype(np.int64), 0, layer.rgba.shape[1] - 1)
    inside = layer.rgba[ti, tj, 3] >= 0.5
    g = layer.inv_depth_at(xs, ys)
    return g[inside] if inside.any() else g.ravel()


def samples_for(c_max_px: float, density: float = 2.5, lo: int = 16, hi: int = 320) -> int:
    """Samples per half aperture for a largest blur diameter ``c_max_px``: ``density`` per px^2 of the half
    disc's area ``pi c^2 / 8``, within [lo, hi]."""
    return int(np.clip(math.ceil(density * math.pi * c_max_px**2 / 8.0), lo, hi))


def render_views(scene: LayeredScene, lens: Lens, effects: Effects, rng: np.random.Generator,
                 samples: ApertureSamples | None = None, density: float = 2.5) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (H, W, 3) float32 left and right views, linear; each ~ half the full-aperture image.

    ``samples`` default: :func:`aperture_samples` sized by the pair's largest blur at the recorded focus
    (:func:`samples_for`)."""
    F = true_focus_mm(lens, effects)
    groups = _channel_groups(lens, effects, F)
    sa = spherical_aberration_px(lens, effects)
    if samples is None:  # sized by the ideal lens's blur, so a planted effect never changes the sampling
        c0, c1 = lens.coc_coefficients()
        samples = aperture_samples(samples_for(max_abs_coc_px(scene, lambda g: c0 + c1 * g, scene.pad), density), rng)
    w = transmission(samples, effects)
    share = left_share(samples, effects)
    wl, wr = w * share, w * (1.0 - share)
    to_dp = misregistration_matrix(effects, scene.size)
    W, H = scene.size
    cats = _CatsEye(effects.get("field_varying_psf"), scene.size) if effects.get("field_varying_psf") else None
    left, right = np.zeros((H, W, 3), np.float32), np.zeros((H, W, 3), np.float32)
    passed = [np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)] if cats else None
    rho2 = samples.rho2
    for gi, (chans, c0, c1) in enumerate(groups):
        comp = _Compositor(scene, chans, c0, c1, to_dp, samples.n_half)
        lv, rv = left[..., chans], right[..., chans]
        for i in range(samples.u.size):
            col = comp.render(samples.u[i], samples.v[i], sa * (rho2[i] - SA_FOCUS_RHO2))
            if cats is None:
                lv += np.float32(wl[i]) * col
                rv += np.float32(wr[i]) * col
            else:
                m = cats.weight(samples.u[i], samples.v[i])
                lv += (np.float32(wl[i]) * m)[..., None] * col
                rv += (np.float32(wr[i]) * m)[..., None] * col
                if gi == 0:
                    passed[0] += np.float32(wl[i]) * m
                    passed[1] += np.float32(wr[i]) * m
    if passed is not None:  # per-view shading correction: each view of a flat field is as bright as without the stop
        left *= (np.float32(wl.sum()) / np.maximum(passed[0], 1e-4))[..., None]
        right *= (np.float32(wr.sum()) / np.maximum(passed[1], 1e-4))[..., None]
    gains = lr_gain_field(effects, scene.size)
    if gains is not None:
        left *= gains[0][..., None]
        right *= gains[1][..., None]
    return left, right


def render_sharp(scene: LayeredScene, lens: Lens, effects: Effects, sharp_f_number: float, rng: np.random.Generator,
                 n_half: int = 16) -> np.ndarray:
    """(H, W, 3) float32 ``sharp``: the whole aperture at ``sharp_f_number`` (0 = all-in-focus, a pinhole),
    focused where the lens really focuses, integrated over pixels; no DP effect reaches it."""
    if sharp_f_number == 0:
        samples, c0, c1 = ApertureSamples(np.zeros(1), np.zeros(1)), 0.0, 0.0
    else:
        small = Lens(lens.focal_length_mm, sharp_f_number, lens.focus_distance_mm, lens.pixel_pitch_mm)
        samples = aperture_samples(n_half, rng)
        c0, c1 = small.coc_coefficients(true_focus_mm(lens, effects))
    W, H = scene.size
    out = np.zeros((H, W, 3), np.float32)
    comp = _Compositor(scene, slice(0, 3), c0, c1, np.eye(3), samples.n_half if samples.u.size > 1 else 1)
    wt = np.float32(1.0 / samples.u.size)
    for i in range(samples.u.size):
        out += wt * comp.render(samples.u[i], samples.v[i], 0.0)
    return out


def add_sensor_noise(rng: np.random.Generator, img: np.ndarray, shot_var: float, read_sigma: float) -> np.ndarray:
    """``img`` plus Gaussian noise of variance ``shot_var * I + read_sigma^2`` per pixel and channel (linear)."""
    var = shot_var * np.clip(img, 0.0, None) + read_sigma**2
    return (img + rng.standard_normal(img.shape) * np.sqrt(var)).astype(np.float32)


def views_noise(effects: Effects, shot_var: float, read_sigma: float) -> tuple[float, float]:
    """The views' (shot variance, read sigma): nominal, or raised by the ``noise`` effect."""
    a = effects.get("noise")
    return shot_var * (1.0 + a), read_sigma * (1.0 + a / 2.0)


def _png16(path: Path, rgb: np.ndarray) -> None:
    v = np.round(np.clip(rgb, 0.0, 1.0) * 65535.0).astype(np.uint16)
    if not cv2.imwrite(str(path), np.ascontiguousarray(v[..., ::-1]) if v.ndim == 3 else v):
        raise OSError(f"could not write {path}")


def canvas_pad(lens_fmin: Lens, effects: Effects, near_mm: float = 500.0, far_mm: float = 7500.0) -> int:
    """Canvas margin (px) that covers the largest blur radius any depth in [near, far] can get at any focus in
    that range at the widest aperture (every colour channel), plus the aberration and misregistration shifts."""
    worst = 0.0
    for F, z in ((far_mm, near_mm), (near_mm, far_mm)):
        for _, c0, c1 in _channel_groups(Lens(lens_fmin.focal_length_mm, lens_fmin.f_number, F, lens_fmin.pixel_pitch_mm), effects, F):
            worst = max(worst, abs(c0 + c1 / z))
    return int(math.ceil(worst / 2 + abs(spherical_aberration_px(lens_fmin, effects)) / 2 + 1.5 * effects.get("misregistration") + 4))


def _splits(n_scenes: int) -> list[str]:
    """Split of each scene: the last ``k`` test, the ``k`` before val, the rest train (k = max(1, round(n / 6)))."""
    k = max(1, round(n_scenes / 6))
    return ["test" if i >= n_scenes - k else ("val" if i >= n_scenes - 2 * k else "train") for i in range(n_scenes)]


def write_dataset(
    out: str | Path,
    effects: str | Sequence[str] | Mapping[str, float] | None = "none",
    strength: float = 1.0,
    *,
    scenes: int = 12,
    size: tuple[int, int] = (256, 170),
    f_numbers: tuple[float, ...] = (1.8, 4.0),
    seed: int = 0,
    noise: bool = True,
    shot_var: float = NOMINAL_SHOT_VAR,
    read_sigma: float = NOMINAL_READ_SIGMA,
    sharp_f_number: float = 22.0,
    focal_length_mm: float = 35.0,
    sensor_width_mm: float = 17.3,
    density: float = 2.5,
) -> dict[str, list[str]]:
    """Write a format-v1 dataset of ``scenes`` x ``f_numbers`` pairs with ``effects`` planted; returns the splits.

    ``effects``: see :meth:`Effects.of` (magnitudes :data:`EFFECT_DEFAULTS` x ``strength``). ``noise`` False
    leaves every image noise-free; otherwise the views get ``(shot_var, read_sigma)`` (raised by the ``noise``
    effect) and ``sharp`` the nominal noise. ``sharp`` is rendered at ``sharp_f_number`` (0 = all-in-focus) and
    params.json states it. Splits by scene (:func:`_splits`). ``planted.json`` at the root records the planted
    magnitudes for benchmarks. The dataset is written to a hidden temporary folder and renamed into place; an
    existing ``out`` is an error (never overwritten).
    """
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out}: already exists; aperture_dp.write_dataset never overwrites a dataset")
    eff = Effects.of(effects, strength)
    W, H = size
    pitch = sensor_width_mm / W
    rng = np.random.default_rng(seed)
    # the canvas (hence the scenes a seed draws) must not depend on what is planted: sized for every effect at
    # strength 2 (or the strongest asked)
    top = max([2.0] + [v / EFFECT_DEFAULTS[k] for k, v in eff.a.items() if EFFECT_DEFAULTS[k]])
    pad = canvas_pad(Lens(focal_length_mm, min(f_numbers), 1000.0, pitch), Effects.of(list(EFFECT_DEFAULTS), top))
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    view_noise = views_noise(eff, shot_var, read_sigma)
    try:
        for si, split in enumerate(_splits(scenes)):
            scene = layered_scene(rng, size, pad)
            depth = scene.pinhole_depth_mm(0)
            fx, fy = scene.focus_px
            F = float(np.median(depth[max(fy - 3, 0) : fy + 4, max(fx - 3, 0) : fx + 4]))
            depth_png = np.clip(np.round(depth), 1, 65535).astype(np.uint16)
            for N in f_numbers:
                lens = Lens(focal_length_mm, float(N), F, pitch)
                left, right = render_views(scene, lens, eff, rng, density=density)
                sharp = render_sharp(scene, lens, eff, sharp_f_number, rng)
                if noise:
                    left, right = (add_sensor_noise(rng, v, *view_noise) for v in (left, right))
                    sharp = add_sensor_noise(rng, sharp, shot_var, read_sigma)
                pid = f"ap{seed}-{si:02d}_ap_f{N:g}"
                d = tmp / "pairs" / pid
                d.mkdir(parents=True)
                _png16(d / "sharp.png", sharp)
                _png16(d / "left.png", left)
                _png16(d / "right.png", right)
                if not cv2.imwrite(str(d / "depth.png"), depth_png):
                    raise OSError(f"could not write {d / 'depth.png'}")
                tifffile.imwrite(d / "depth.tif", depth.astype(np.float32))
                tifffile.imwrite(d / "coc.tif", lens.coc_px(depth).astype(np.float32))
                params = {"pair_id": pid, "scene": f"ap{seed}-{si:02d}", "camera": "ap", "f_number": float(N),
                          "focus_distance_mm": F, "focal_length_mm": focal_length_mm, "pixel_pitch_mm": pitch,
                          "focus_point_px": [fx, fy], "image_size": [W, H], "sharp_f_number": float(sharp_f_number)}
                (d / "params.json").write_text(json.dumps(params, indent=1))
                splits[split].append(pid)
        index = {"format": "dp5k-dataset", "version": 1, "splits": splits, "generator": "dp5k_testing.aperture_dp"}
        (tmp / "dataset.json").write_text(json.dumps(index, indent=1))
        planted = {"generator": "dp5k_testing.aperture_dp", "effects": eff.a, "strength": strength, "seed": seed,
                   "noise": noise, "nominal_noise": {"shot_var": shot_var, "read_sigma": read_sigma},
                   "note": "what was planted, for benchmarks; dp5k diagnose never reads this file"}
        (tmp / "planted.json").write_text(json.dumps(planted, indent=1))
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return splits


def write_matrix_cell(out: str | Path, effects: str | Sequence[str] | Mapping[str, float] | None, strength: float = 1.0,
                      seed: int = 0, size: tuple[int, int] = (128, 86), pairs: int = 8) -> Path:
    """One small confusion-matrix cell quickly: ``pairs`` pairs (scenes x f/1.8, f/4; at least 3 scenes so that
    train, val and test each get one) at ``size`` with ``effects`` at ``strength``. Returns ``out``."""
    write_dataset(out, effects, strength, scenes=max(3, pairs // 2), size=size, seed=seed)
    return Path(out)
