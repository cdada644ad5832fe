"""A third independent DP renderer: pupil-function PSFs (geometric ray aberrations) and layered "over" occlusion.

`dp5k diagnose` must name the effects an outside renderer plants. :mod:`dp5k_testing.foreign_dp` scatters flat
half discs without occlusion and :mod:`dp5k_testing.aperture_dp` gathers sub-aperture views through a z-buffer;
this module models image formation a third way and shares no code with them or with dp5k (numpy, OpenCV,
tifffile, json). It is held out: diagnose is never tuned on it.

**Pupil function.** Each view's PSF at a signed CoC ``c`` (output px, Eq. 6 divided by the pitch; > 0 behind
focus) comes from a sampled pupil. A ray through the normalized pupil point ``u = (u_x, u_y)`` (``|u| <= 1``,
x right and y down like the image) carries the weight ``T(u) R_view(u)`` and lands at the gradient of the
wavefront ``W(u)`` (px: its gradient over the normalized pupil is the landing offset in px) from the point's chief
ray (docs/conventions.md)::

    W(u) = c/4 |u|^2                                            defocus: lands at c u / 2
         + s3 (|u|^4/4 - 3/10 |u|^2) + s5 (|u|^6/6 - 3/14 |u|^2)   spherical aberration (front_back_asymmetry)
         + A/4 u^T [[x^2 - y^2, 2xy], [2xy, y^2 - x^2]] u          astigmatism at field (x, y) (field_varying_psf)

* ``T(u)`` is the pupil's transmission: 1 inside the unit disc (the aperture stop) times the pixel's angular
  acceptance (``psf_profile``). ``R_L(u)`` is the left photodiode's response: ideally the hard step ``u_x < 0``
  (the microlens images the pupil onto the photodiode pair), ``R_R(u) = R_L(-u)`` and ``R_L + R_R = 1``.
* The pupil is sampled on a square lattice of ``n x n`` cells, ``n`` even (so ``u_x = 0`` is a cell boundary: the
  split is exact) and chosen so that neighbouring rays land at most 1/6 px apart; cells cut by the rim are split
  4 x 4 and weighted by their area inside the disc. Each ray's weight is spread over its cell's image (a square
  of the cell's size mapped by the defocus) and integrated over pixel areas exactly (box): the **kernel is the
  pixel-area integral of the geometric PSF** of a point at the source pixel's centre (so, as in the area-coverage
  kernels of Eq. 2, a disc under 1 px across stays in its pixel), normalised so that the full pupil (``R_L + R_R``)
  sums to 1: the camera's exposure is set through the lens, so each ideal view sums to 1/2.
* **Clean data is Eq. 2**: with nothing planted each view is the radiance convolved with the flat half disc of
  diameter ``|c|`` split at its centre line (for c > 0 the left view gets the left half), ``L + R`` the full disc,
  each summing to 1/2, up to the pupil sampling (about 1e-3 of the kernel's peak). No diffraction is modelled.
* Kernels are cached by quantised CoC node: 0.1 px apart up to |c| = 2 px, 3 % apart beyond; a pixel between two
  nodes sends its light through both kernels in proportion (linear blend of the scatter), so slanted planes have
  no steps.

**Occlusion (layered compositing).** A scene (:mod:`dp5k_testing.pupil_scene`) is a stack of planar layers, each
with colour, coverage alpha and an inverse depth per pixel. Back to front, each layer's premultiplied colour
``alpha * colour`` is scattered through its own (depth-varying) kernels into ``P_v`` and its alpha through the
same kernels normalised to a sum of 1 into ``A_v`` (the share of view ``v``'s ray cone that the layer blocks),
and the view becomes ``P_v + (1 - A_v) * view`` ("over"). A blurred near layer thus hides what lies behind it
(only its defocused rim lets the far scene through, by the share of rays that pass it), unlike a scatter without
occlusion and unlike a per-ray z-buffer.

**Effects** (``dp5k_common.effects.EFFECT_NAMES``): magnitude ``a`` = :data:`EFFECT_DEFAULTS` x strength.
Lengths on the sensor are in mm and become px through the pitch (at the default 36 mm / 256 px = 0.14 mm / px).
Field coordinates: ``x_n = (x - cx) / cx``, ``y_n = (y - cy) / cy`` (frame edges at +-1); the field vector for
aberrations is normalized by the half-diagonal (corners at radius 1).

* ``lr_gain_imbalance`` (a = 0.06): the photodiodes' quantum efficiency drifts over the sensor (the microlens
  offset for the chief ray angle does not match): left gain ``1 + a s``, right ``1 - a s`` with
  ``s = 0.2 + x_n (1 - 0.3 x_n^2) / 0.7 + 0.35 y_n^2`` (the L/R ratio 1.024 at the centre, 1.16-1.21 along the
  right edge, 0.91-0.95 along the left one, growing toward the top and bottom: not linear). Brightness only,
  applied on the sensor; the views' sum is unchanged where they agree (in focus).
* ``field_varying_psf`` (a = 0.35 mm): astigmatism. At f/2 the sagittal and tangential foci split by a CoC of
  ``a r^2`` mm (r the field radius, corners 1), scaling as ``2 / N``; the medial focus stays flat. Discs become
  ellipses, long along the field's radius behind focus (short in front); at focus a corner point is a disc of
  ``a r^2`` mm. Rays are only redistributed: each view's brightness is unchanged. Kernels at 5 x 5 field nodes
  (bilinear weights on the source).
* ``chromatic_defocus`` (a = 0.45 mm): longitudinal colour of an achromat (secondary spectrum): every depth's
  image lies ``0.55 a`` (red) and ``a`` (blue) mm farther from the lens than the green one, so red and blue focus
  at other distances than green, on the same side (``c = A (v_sensor - v_channel) / v_channel``, ``A = f / N``):
  about -0.8 px (red) and -1.5 px (blue) of CoC at f/2, half that at f/4; green is the lens of Eq. 6.
* ``disparity_scale`` (a = 0.16): a soft split. The photodiodes' angular response is a raised-cosine step over ray
  angles ``tan(theta_x)`` in [-a, a] (the microlens' blur of the pupil image): in pupil coordinates a ramp of half
  width ``2 N a``, ``R_L(u) = (1 - sin(pi/2 clip(u_x / (2 N a), -1, 1))) / 2``. ``L + R`` is unchanged; the DP
  disparity falls to about 0.90 x at f/2 and 0.66 x at f/4 (the ramp covers more of a smaller pupil).
* ``focus_offset`` (a = 0.3 mm): the sensor sits ``a`` mm farther from the lens than the image of the recorded
  focus distance (a back-focus error): every CoC grows by about ``A a / v`` (1.0 px at f/2, 0.5 px at f/4 at the
  defaults), so the lens really focuses nearer than params.json says. ``sharp`` (same lens) has it too.
* ``psf_profile`` (a = 1.1): the pixel's angular acceptance falls off with the ray's angle: ``T(u) = exp(-a
  (2 |u| / N)^2)`` (``tan(theta) = |u| / 2N``): at f/2 the disc's rim gets 0.33 of its centre's light, at f/4
  0.76 (centre-heavy, soft-edged discs at both sides of focus); exposure-normalised (kernel sums unchanged).
* ``front_back_asymmetry`` (a = 0.4 mm): under-corrected spherical aberration. ``s3 = a (2/N)^3`` mm,
  ``s5 = -0.25 a (2/N)^5`` mm (a zonal residue); each term's defocus balance (3/5, 3/7) keeps the two views'
  mean ray landing equal at the recorded focus, where the camera's phase-detect AF put it (binning the
  sub-pixel focused spot into pixels leaves 0.09 px of L/R centroid separation there at f/2, none at f/4). Behind focus the rim's rays spread outwards:
  centre-heavy discs; in front they crowd: bright-rimmed, smaller discs (at f/2 and 10 px the centre/rim ratio of
  the disc is about 2.3 behind and 0.46 in front). The L/R centroid separation is unchanged; at focus the f/2
  spot spreads by about 0.2 px rms.
* ``misregistration`` (a = 1.0): both views against ``sharp`` by a similarity about the frame centre: shifted by
  ``(0.55 a, -0.35 a) W / 256`` px, rotated by ``0.05 a`` degrees, scaled by ``1 + 0.0012 a`` (Lanczos resampling
  of the noise-free views).
* ``noise`` (a = 1.2): the DP frames exposed ``1 + a`` times shorter and pushed digitally: shot variance x
  ``(1 + a)``, read sigma x ``(1 + a)``: at intensity 0.25 the variance is :func:`noise_ratio` = 2.6 x nominal.

**Sensor.** Gaussian shot + read noise on every channel of both views (variance ``shot_var I + read_sigma^2``) and
of ``sharp``, nominally :data:`NOMINAL_SHOT_VAR` = 5e-5 and :data:`NOMINAL_READ_SIGMA` = 1.5e-3
(``dp5k diagnose --nominal-noise 5e-5,1.5e-3``), then 16-bit quantisation. ``sharp`` is the full pupil at
``sharp_f_number`` (default 22, through the same lens: its focus error, colour and scaled aberrations; no DP
effect) or the all-in-focus radiance (0); params.json says which.

**Writer** (:func:`write_dataset`): format v1 by hand (OpenCV PNGs, tifffile, json) into a hidden folder renamed
into place (never overwriting), splits by scene, ``planted.json`` at the root (what was planted; diagnose never
reads it). Scenes and noise are drawn from seed-derived streams that do not depend on what is planted.
"""

from __future__ import annotations

import functools
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

from .pupil_scene import REFERENCE_WIDTH_PX, LayerScene, layer_scene

EFFECT_DEFAULTS: dict[str, float] = {
    "lr_gain_imbalance": 0.06,  # L gain 1 + a s(x, y), R 1 - a s, s = 0.2 + x_n (1 - 0.3 x_n^2) / 0.7 + 0.35 y_n^2
    "field_varying_psf": 0.35,  # astigmatism: sagittal/tangential CoC split a r^2 mm at f/2 (x 2/N), r = 1 at corners
    "chromatic_defocus": 0.45,  # image distance of red +0.55 a mm, of blue +a mm behind green's
    "disparity_scale": 0.16,  # photodiode response: raised-cosine step over tan(angle) in [-a, a]
    "focus_offset": 0.3,  # sensor a mm behind the image of the recorded focus distance
    "psf_profile": 1.1,  # angular acceptance T = exp(-a (2 rho / N)^2)
    "front_back_asymmetry": 0.4,  # spherical aberration s3 = a (2/N)^3 mm, s5 = -0.25 a (2/N)^5 mm (ray aberration)
    "misregistration": 1.0,  # shift (0.55, -0.35) a W/256 px, rotation 0.05 a deg, scale 1 + 0.0012 a
    "noise": 1.2,  # shot variance x (1 + a), read sigma x (1 + a)
}
NOMINAL_SHOT_VAR = 5e-5
"""Nominal shot-noise variance per unit linear intensity (each view, each channel, and sharp)."""
NOMINAL_READ_SIGMA = 1.5e-3
"""Nominal read-noise standard deviation (linear units)."""
REFERENCE_F_NUMBER = 2.0
"""Aberration magnitudes are stated at this f-number (astigmatism scales as 1/N, spherical as 1/N^3 and 1/N^5)."""
RAYS_PER_PX = 6
"""Neighbouring rays land at most 1/RAYS_PER_PX px apart."""
FINE_STEP_PX = 0.1
"""CoC node spacing up to :data:`FINE_LIMIT_PX`."""
FINE_LIMIT_PX = 2.0
COARSE_RATIO = 1.03
"""CoC node ratio beyond :data:`FINE_LIMIT_PX`."""
FIELD_NODES = (5, 5)
"""Field nodes (x, y) over the canvas when a PSF varies over the field: odd, so the centre is a node (no
astigmatism there), and fine enough that bilinear weights follow the astigmatism's r^2 growth (a point at the
frame's side edge gets its ellipse's second moments within 2 %)."""
SA5_RATIO = -0.25
"""Fifth-order spherical aberration as a multiple of the third-order one (at the reference f-number)."""

LEFT, RIGHT, FULL = 1, -1, 0
"""View codes: the left photodiode (pupil u_x < 0), the right one, both (a normal pixel: ``sharp``)."""


# ---------------------------------------------------------------------------------------------------- effects
@dataclass
class Effects:
    """Planted effects with their magnitudes (:data:`EFFECT_DEFAULTS` x strength)."""

    a: dict[str, float]

    @classmethod
    def of(cls, spec: str | Sequence[str] | Mapping[str, float] | None, strength: float = 1.0) -> "Effects":
        """``spec``: ``None``/``"none"``, names joined by ``+``, a list of names (each at its default times
        ``strength``), or a mapping name -> its own strength (times ``strength``)."""
        if isinstance(spec, Mapping):
            per = {str(k): float(v) for k, v in spec.items()}
        else:
            names = [] if spec in (None, "none", "") else (spec.split("+") if isinstance(spec, str) else list(spec))
            per = {n: 1.0 for n in names if n != "none"}
        unknown = [n for n in per if n not in EFFECT_DEFAULTS]
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; known: {', '.join(EFFECT_DEFAULTS)}")
        return cls({n: EFFECT_DEFAULTS[n] * s * strength for n, s in per.items() if s * strength != 0})

    def get(self, name: str) -> float:
        return float(self.a.get(name, 0.0))


# ---------------------------------------------------------------------------------------------------- lens
@dataclass(frozen=True)
class Lens:
    """One capture's thin lens. Lengths in mm; ``pixel_pitch_mm`` is the output image's pitch."""

    focal_length_mm: float
    f_number: float
    focus_distance_mm: float
    pixel_pitch_mm: float

    @property
    def aperture_mm(self) -> float:
        return self.focal_length_mm / self.f_number

    def image_distance_mm(self, inv_depth: np.ndarray | float) -> np.ndarray | float:
        """Thin-lens image distance of an object at inverse depth ``inv_depth`` (1/mm)."""
        return 1.0 / (1.0 / self.focal_length_mm - inv_depth)

    def sensor_distance_mm(self, sensor_shift_mm: float = 0.0) -> float:
        """Lens-to-sensor distance: the image of the recorded focus distance, plus a back-focus error."""
        return float(self.image_distance_mm(1.0 / self.focus_distance_mm)) + sensor_shift_mm

    def coc_px(self, depth_mm: np.ndarray) -> np.ndarray:
        """Eq. 6 at the recorded focus: ``f^2 (d - F) / (N d (F - f))`` / pitch (> 0 behind focus)."""
        f, F = self.focal_length_mm, self.focus_distance_mm
        return f * f * (depth_mm - F) / (self.f_number * depth_mm * (F - f)) / self.pixel_pitch_mm

    def inv_depth_for_coc(self, coc_px: float | np.ndarray) -> float | np.ndarray:
        """Inverse depth (1/mm) whose Eq. 6 CoC at the recorded focus is ``coc_px`` (inverts :meth:`coc_px`)."""
        A = self.aperture_mm
        v = A * self.sensor_distance_mm() / (np.asarray(coc_px) * self.pixel_pitch_mm + A)
        return 1.0 / self.focal_length_mm - 1.0 / v

    def channel_coc_px(self, inv_depth: np.ndarray, sensor_shift_mm: float = 0.0, image_shift_mm: float = 0.0
                       ) -> np.ndarray:
        """Signed CoC (px) of a colour channel whose images lie ``image_shift_mm`` farther from the lens, on a sensor
        ``sensor_shift_mm`` behind the image of the recorded focus: ``A (v_s - v_c) / v_c``. Both 0: Eq. 6."""
        vc = self.image_distance_mm(inv_depth) + image_shift_mm
        return self.aperture_mm * (self.sensor_distance_mm(sensor_shift_mm) - vc) / vc / self.pixel_pitch_mm


@dataclass(frozen=True)
class Optics:
    """The PSF parameters of one capture (px unless stated), fixed over the frame except the astigmatism.

    Attributes:
        sa3_px, sa5_px: spherical aberration (ray aberration coefficients of rho^2 and rho^4).
        astig_px: astigmatic CoC split at field radius 1 (corners).
        apod: angular-acceptance exponent: ``T = exp(-apod |u|^2)``.
        split_w: half width of the photodiodes' soft split in pupil units (0: hard step).
    """

    sa3_px: float = 0.0
    sa5_px: float = 0.0
    astig_px: float = 0.0
    apod: float = 0.0
    split_w: float = 0.0


def optics_of(lens: Lens, effects: Effects, dual_pixel: bool = True) -> Optics:
    """The PSF parameters at ``lens``'s f-number (aberrations scaled from :data:`REFERENCE_F_NUMBER`). Without
    ``dual_pixel`` (a normal pixel, ``sharp``) there is no split."""
    k = REFERENCE_F_NUMBER / lens.f_number
    p = lens.pixel_pitch_mm
    fba = effects.get("front_back_asymmetry")
    return Optics(
        sa3_px=fba * k**3 / p,
        sa5_px=SA5_RATIO * fba * k**5 / p,
        astig_px=effects.get("field_varying_psf") * k / p,
        apod=effects.get("psf_profile") * (2.0 / lens.f_number) ** 2,
        split_w=2.0 * lens.f_number * effects.get("disparity_scale") if dual_pixel else 0.0,
    )


# ---------------------------------------------------------------------------------------------------- pupil
@functools.lru_cache(maxsize=128)
def pupil_lattice(n: int, rim_split: int = 4, rim_samples: int = 8) -> tuple[np.ndarray, ...]:
    """Rays over the unit disc: ``(u_x, u_y, area, half_size)``, ``n`` x ``n`` cells of side ``2 / n`` (``n`` even, so
    ``u_x = 0`` is a cell boundary); cells cut by the rim are split ``rim_split`` x ``rim_split``, each weighted by
    its area inside the disc (``rim_samples``^2 samples). ``half_size`` is each ray's half cell side (pupil units)."""
    h = 2.0 / n
    c = -1.0 + h * (np.arange(n) + 0.5)
    ux, uy = np.meshgrid(c, c)
    near = np.hypot(np.maximum(np.abs(ux) - h / 2, 0), np.maximum(np.abs(uy) - h / 2, 0))
    far = np.hypot(np.abs(ux) + h / 2, np.abs(uy) + h / 2)
    full = far <= 1.0
    rim = (near < 1.0) & ~full
    hs = h / rim_split
    off = -h / 2 + hs * (np.arange(rim_split) + 0.5)
    ox, oy = np.meshgrid(off, off)
    sx = (ux[rim][:, None] + ox.ravel()[None, :]).ravel()
    sy = (uy[rim][:, None] + oy.ravel()[None, :]).ravel()
    o2 = -hs / 2 + hs / rim_samples * (np.arange(rim_samples) + 0.5)
    qx, qy = sx[:, None, None] + o2[None, None, :], sy[:, None, None] + o2[None, :, None]
    cov = (qx * qx + qy * qy <= 1.0).mean((1, 2))
    keep = cov > 0
    return (np.concatenate([ux[full], sx[keep]]), np.concatenate([uy[full], sy[keep]]),
            np.concatenate([np.full(int(full.sum()), h * h), cov[keep] * hs * hs]),
            np.concatenate([np.full(int(full.sum()), h / 2), np.full(int(keep.sum()), hs / 2)]))


def photodiode_response(ux: np.ndarray, view: int, split_w: float) -> np.ndarray:
    """Share of a ray through pupil x ``ux`` that ``view`` collects: the left photodiode takes ``u_x < 0`` (hard
    step), or a raised-cosine ramp of half width ``split_w``; the right one the mirror; ``FULL`` everything."""
    if view == FULL:
        return np.ones_like(ux)
    s = -view * ux  # > 0 on the view's own side
    if split_w <= 0:
        return (s > 0).astype(np.float64)
    return 0.5 + 0.5 * np.sin(0.5 * np.pi * np.clip(s / split_w, -1.0, 1.0))


def ray_landing(ux: np.ndarray, uy: np.ndarray, c: float, sa3: float, sa5: float, ac: float, as_: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Landing offset (px) of each ray from the chief ray: the gradient of the wavefront (module docstring).
    ``ac, as_``: the astigmatic terms ``A (x^2 - y^2)`` and ``A 2 x y`` at the field point."""
    rho2 = ux * ux + uy * uy
    radial = 0.5 * c + sa3 * (rho2 - 0.6) + sa5 * (rho2 * rho2 - 3.0 / 7.0)
    return radial * ux + 0.5 * (ac * ux + as_ * uy), radial * uy + 0.5 * (as_ * ux - ac * uy)


def _box_split(x: np.ndarray, half: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel index (offset by ``radius``) of the left/upper pixel a footprint [x - half, x + half] touches, and the
    share of it there (footprints are at most 1 px wide, so they touch at most two pixels)."""
    lo = x - half
    i0 = np.floor(lo + 0.5)
    with np.errstate(divide="ignore", invalid="ignore"):
        f0 = np.where(half > 0, np.clip((i0 + 0.5 - lo) / (2.0 * half), 0.0, 1.0), 1.0)
    return i0.astype(np.int64) + radius, f0


@functools.lru_cache(maxsize=1024)
def _ray_masses(n: int, view: int, apod: float, split_w: float) -> np.ndarray:
    """Each lattice ray's share of the light ``view`` collects: ``area T(u) R_view(u)`` over the full pupil's total."""
    ux, uy, area, _ = pupil_lattice(n)
    t = area * np.exp(-apod * (ux * ux + uy * uy)) if apod else area
    return t * photodiode_response(ux, view, split_w) / t.sum()


@functools.lru_cache(maxsize=60000)
def psf(c: float, view: int, optics: Optics, ac: float = 0.0, as_: float = 0.0) -> np.ndarray:
    """(2r+1, 2r+1) float32 kernel of ``view`` for a point at CoC ``c`` px, centred on the point's pixel,
    integrated over pixel areas; the full pupil's kernel sums to 1 (an ideal view's to 1/2)."""
    o = optics
    ext = 0.5 * abs(c) + 0.6 * (abs(o.sa3_px) + abs(o.sa5_px)) + 0.5 * math.hypot(ac, as_)  # bounds the ray spread
    n = max(16, 2 * int(math.ceil(RAYS_PER_PX * ext)))
    ux, uy, _, half = pupil_lattice(n)
    mass = _ray_masses(n, view, o.apod, o.split_w)
    ex, ey = ray_landing(ux, uy, c, o.sa3_px, o.sa5_px, ac, as_)
    foot = half * ext  # a cell's image: the pupil cell scaled by the ray spread
    reach = float(max(np.abs(ex).max(), np.abs(ey).max()) + foot.max())
    r = int(math.ceil(reach + 0.5))
    size = 2 * r + 1
    ix, fx = _box_split(ex, foot, r)
    iy, fy = _box_split(ey, foot, r)
    base = iy * size + ix
    idx = np.concatenate([base, base + 1, base + size, base + size + 1])
    gx, gy = 1.0 - fx, 1.0 - fy
    w = np.concatenate([mass * fx * fy, mass * gx * fy, mass * fx * gy, mass * gx * gy])
    keep = w > 0
    k = np.bincount(idx[keep], weights=w[keep], minlength=size * size)[: size * size].reshape(size, size)
    nz = np.nonzero(k.sum(0) + k.sum(1))[0]  # crop to the support, keeping the centre
    m = int(max(abs(nz[0] - r), abs(nz[-1] - r))) if nz.size else 0
    return np.ascontiguousarray(k[r - m : r + m + 1, r - m : r + m + 1], dtype=np.float32)


# ---------------------------------------------------------------------------------------------------- nodes
def coc_nodes(limit_px: float = 200.0) -> np.ndarray:
    """Sorted CoC nodes (px): every :data:`FINE_STEP_PX` up to :data:`FINE_LIMIT_PX`, then x :data:`COARSE_RATIO`."""
    fine = np.arange(0.0, FINE_LIMIT_PX + 1e-9, FINE_STEP_PX)
    coarse = [FINE_LIMIT_PX]
    while coarse[-1] < limit_px:
        coarse.append(coarse[-1] * COARSE_RATIO)
    pos = np.unique(np.round(np.concatenate([fine, coarse[1:]]), 6))
    return np.concatenate([-pos[:0:-1], pos])


NODES = coc_nodes()


def node_weights(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index ``i`` of the node below each CoC and the weight ``t`` of node ``i + 1`` (linear between nodes)."""
    i = np.clip(np.searchsorted(NODES, c, side="right") - 1, 0, NODES.size - 2)
    lo, hi = NODES[i], NODES[i + 1]
    return i, np.clip((c - lo) / (hi - lo), 0.0, 1.0)


# ---------------------------------------------------------------------------------------------------- field
@dataclass
class FieldGrid:
    """Field nodes for PSFs that vary over the field: node (i, j) at canvas (xs[i], ys[j]) with bilinear (hat)
    weights ``hx[i][col] * hy[j][row]``; the astigmatic terms ``ac, as_`` of each node (px)."""

    xs: np.ndarray
    ys: np.ndarray
    hx: list[np.ndarray]
    hy: list[np.ndarray]
    terms: dict[tuple[int, int], tuple[float, float]]


def field_grid(scene: LayerScene, optics: Optics) -> FieldGrid | None:
    """None without astigmatism; else :data:`FIELD_NODES` nodes spanning the canvas with their astigmatic terms
    ``A (x^2 - y^2)`` and ``A 2 x y`` (field (x, y) from the frame centre over the half-diagonal)."""
    if optics.astig_px == 0:
        return None
    hc, wc = scene.canvas_shape
    W, H = scene.size
    p = scene.pad
    cx, cy = (W - 1) / 2, (H - 1) / 2
    diag = math.hypot(cx, cy)
    nx, ny = FIELD_NODES
    xs = np.linspace(0, wc - 1, nx)  # canvas px
    ys = np.linspace(0, hc - 1, ny)

    def hats(nodes: np.ndarray, length: int) -> list[np.ndarray]:
        coord = np.arange(length, dtype=np.float64)
        step = nodes[1] - nodes[0]
        return [np.clip(1.0 - np.abs(coord - v) / step, 0.0, 1.0).astype(np.float32) for v in nodes]

    terms = {}
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            xn, yn = (x - p - cx) / diag, (y - p - cy) / diag
            A = optics.astig_px
            terms[(i, j)] = (round(A * (xn * xn - yn * yn), 6), round(A * 2 * xn * yn, 6))
    return FieldGrid(xs, ys, hats(xs, wc), hats(ys, hc), terms)


def field_coordinates(size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) ``x_n, y_n``: frame px relative to the centre, edges at -1 and +1."""
    W, H = size
    x = (np.arange(W) - (W - 1) / 2) / ((W - 1) / 2)
    y = (np.arange(H) - (H - 1) / 2) / ((H - 1) / 2)
    return np.broadcast_to(x[None, :], (H, W)), np.broadcast_to(y[:, None], (H, W))


def lr_gains(effects: Effects, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """(H, W) gains of the left and right photodiodes (``lr_gain_imbalance``), or None."""
    a = effects.get("lr_gain_imbalance")
    if not a:
        return None
    xn, yn = field_coordinates(size)
    s = 0.2 + xn * (1.0 - 0.3 * xn * xn) / 0.7 + 0.35 * yn * yn
    return (1.0 + a * s).astype(np.float32), (1.0 - a * s).astype(np.float32)


def misregistration_matrix(effects: Effects, size: tuple[int, int]) -> np.ndarray | None:
    """2 x 3 affine map from ``sharp``'s frame px to where that content lies in the views (None if not planted)."""
    a = effects.get("misregistration")
    if not a:
        return None
    W, H = size
    cx, cy = (W - 1) / 2, (H - 1) / 2
    th = math.radians(0.05 * a)
    m = 1.0 + 0.0012 * a
    R = m * np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    t = np.array([cx, cy]) - R @ np.array([cx, cy]) + np.array([0.55, -0.35]) * a * W / REFERENCE_WIDTH_PX
    return np.hstack([R, t[:, None]])


# ---------------------------------------------------------------------------------------------------- render
def _channel_groups(effects: Effects) -> list[tuple[list[int], float]]:
    """Channels sharing one CoC map, with their image distance behind green's (mm)."""
    a = effects.get("chromatic_defocus")
    if not a:
        return [([0, 1, 2], 0.0)]
    return [([0], 0.55 * a), ([1], 0.0), ([2], a)]


ROW_BLOCK = 32
"""Rows per piece when a CoC node's pixels form a diagonal band (keeps the boxes convolved small)."""
DENSE = 0.4
"""A piece whose pixels fill less than this share of its box (and is taller than ROW_BLOCK) is split by rows."""


def composite(scene: LayerScene, lens: Lens, effects: Effects, views: Sequence[int], dual_pixel: bool = True
              ) -> dict[int, np.ndarray]:
    """Canvas images (Hc, Wc, 3) float32 of ``views`` (LEFT, RIGHT, FULL) by layered "over" compositing, each layer
    scattered through its kernels (module docstring); no sensor effect (gain, misregistration, noise).

    Each covered pixel of a layer sends ``alpha * colour`` (and ``alpha``) through the kernels of the two CoC nodes
    around its CoC (linear weights) and, with a field-varying PSF, of the four field nodes around it (bilinear
    weights). Pixels are grouped by (CoC node, field cell) and each group is convolved on its box (split into blocks
    of rows where its pixels are a thin diagonal band). A view's kernels sum to :func:`view_share` exactly (the
    pupil lattice is mirror-symmetric), so the alpha channel scattered with them, divided by it, is the share of the
    view's ray cone the layer blocks."""
    hc, wc = scene.canvas_shape
    optics = optics_of(lens, effects, dual_pixel)
    groups = _channel_groups(effects)
    grid = field_grid(scene, optics)
    shift = effects.get("focus_offset")
    out = {v: np.zeros((hc, wc, 3), np.float32) for v in views}
    hidden = _hidden_masks(scene, lens, effects, optics)
    for layer, cut in zip(scene.layers, hidden):
        rows, cols = np.nonzero((layer.alpha > 0) & ~cut)
        if rows.size == 0:
            continue
        alpha = layer.alpha[rows, cols]
        colour = layer.colour[rows, cols]
        if grid is None:
            cell, ncell, nx = np.zeros(rows.size, np.int64), 1, 1
        else:
            nx, ny = len(grid.xs) - 1, len(grid.ys) - 1
            ci = np.clip(np.searchsorted(grid.xs, cols, side="right") - 1, 0, nx - 1)
            cj = np.clip(np.searchsorted(grid.ys, rows, side="right") - 1, 0, ny - 1)
            cell, ncell = cj * nx + ci, nx * ny
        for chans, dv in groups:
            n = len(chans)
            acc = {v: np.zeros((hc, wc, n + 1), np.float32) for v in views}  # premultiplied colour, then alpha
            idx, t = node_weights(lens.channel_coc_px(layer.inv_depth[rows, cols], shift, dv))
            pix = np.tile(np.arange(rows.size), 2)
            wts = np.concatenate([(1.0 - t) * alpha, t * alpha]).astype(np.float32)
            key = np.concatenate([idx, idx + 1]) * ncell + cell[pix]
            live = wts > 0
            key, wts, pix = key[live], wts[live], pix[live]
            order = np.argsort(key, kind="stable")
            key, wts, pix = key[order], wts[order], pix[order]
            starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
            col_all = colour[:, chans]
            for s0, s1 in zip(starts, np.r_[starts[1:], key.size]):
                k, cl = divmod(int(key[s0]), ncell)
                cnode = float(NODES[k])
                if grid is None:
                    corners = [(0.0, 0.0, None, None)]
                else:
                    i0, j0 = cl % nx, cl // nx
                    corners = [(*grid.terms[(i, j)], i, j) for j in (j0, j0 + 1) for i in (i0, i0 + 1)]
                kern = [{v: psf(cnode, v, optics, ac, as_) for v in views} for ac, as_, _, _ in corners]
                R = max(K.shape[0] for ks in kern for K in ks.values()) // 2
                for pp, ww in _pieces(rows, cols, pix[s0:s1], wts[s0:s1]):
                    r, c = rows[pp], cols[pp]
                    r0, c0 = int(r.min()) - R, int(c.min()) - R  # canvas corner of the padded box
                    h, w = int(r.max()) + R + 1 - r0, int(c.max()) + R + 1 - c0
                    src = np.zeros((h, w, n + 1), np.float32)
                    src[r - r0, c - c0, :n] = col_all[pp] * ww[:, None]
                    src[r - r0, c - c0, n] = ww
                    y0, x0, y1, x1 = max(r0, 0), max(c0, 0), min(r0 + h, hc), min(c0 + w, wc)
                    for (_, _, i, j), ks in zip(corners, kern):
                        if i is None:
                            part = src
                        else:
                            fy = _window(grid.hy[j], r0, h)
                            fx = _window(grid.hx[i], c0, w)
                            if not (fy.any() and fx.any()):
                                continue
                            part = src * (fy[:, None] * fx[None, :])[..., None]
                        for v in views:
                            # filter2D correlates: the flipped kernel convolves (a point's light lands at +offset)
                            conv = cv2.filter2D(part, cv2.CV_32F, _flipped(ks[v]), borderType=cv2.BORDER_CONSTANT)
                            acc[v][y0:y1, x0:x1] += conv.reshape(h, w, n + 1)[y0 - r0 : y1 - r0, x0 - c0 : x1 - c0]
            for v in views:
                a = acc[v][..., n:] * np.float32(1.0 / view_share(v))
                ch = slice(chans[0], chans[-1] + 1)
                out[v][..., ch] = acc[v][..., :n] + (1.0 - a) * out[v][..., ch]
    return out


def view_share(view: int) -> float:
    """The light a view's kernel collects: 1/2 for each photodiode, 1 for both."""
    return 1.0 if view == FULL else 0.5


def _window(hat: np.ndarray, start: int, length: int) -> np.ndarray:
    """``hat[start : start + length]`` with zeros outside the canvas."""
    out = np.zeros(length, np.float32)
    a, b = max(start, 0), min(start + length, hat.size)
    if b > a:
        out[a - start : b - start] = hat[a:b]
    return out


def _flipped(K: np.ndarray) -> np.ndarray:
    """The kernel rotated by 180 degrees (contiguous), for ``cv2.filter2D``."""
    return np.ascontiguousarray(K[::-1, ::-1])


def _hidden_masks(scene: LayerScene, lens: Lens, effects: Effects, optics: Optics) -> list[np.ndarray]:
    """Per layer, the canvas pixels whose light cannot reach any view: a nearer layer is opaque (alpha 1) over a
    disc around them wider than both layers' blur radii, so its blurred alpha is 1 wherever their kernel lands and
    ``1 - A`` removes them exactly. Skipping them changes nothing but the time."""
    reach = []
    for layer in scene.layers:
        c = lens.channel_coc_px(layer.inv_depth[layer.alpha > 0], effects.get("focus_offset"), 0.0)
        grow = abs(lens.aperture_mm * effects.get("chromatic_defocus") / lens.sensor_distance_mm())
        grow /= lens.pixel_pitch_mm
        aberration = 0.6 * (abs(optics.sa3_px) + abs(optics.sa5_px)) + optics.astig_px  # astigmatism: r^2 / 2 < 1
        reach.append(0.5 * (float(np.abs(c).max(initial=0.0)) + grow) + aberration + 2.0)
    masks = []
    for i, layer in enumerate(scene.layers):
        cut = np.zeros(scene.canvas_shape, bool)
        for j in range(i + 1, len(scene.layers)):
            solid = (scene.layers[j].alpha >= 1.0).astype(np.uint8)
            rad = int(math.ceil(reach[i] + reach[j]))
            if solid.sum() == 0 or rad > 0.25 * min(solid.shape):
                continue
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))
            cut |= cv2.erode(solid, k, borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
        masks.append(cut)
    return masks


def _pieces(rows: np.ndarray, cols: np.ndarray, pix: np.ndarray, wts: np.ndarray):
    """The group's pixels (indices ``pix`` into ``rows, cols``, weights ``wts``) as one piece, or by blocks of
    :data:`ROW_BLOCK` rows when they fill less than :data:`DENSE` of their box."""
    r = rows[pix]
    c = cols[pix]
    h = int(r.max()) - int(r.min()) + 1
    if h <= ROW_BLOCK or pix.size >= DENSE * h * (int(c.max()) - int(c.min()) + 1):
        yield pix, wts
        return
    block = (r - int(r.min())) // ROW_BLOCK
    order = np.argsort(block, kind="stable")
    block, pix, wts = block[order], pix[order], wts[order]
    starts = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])
    for s0, s1 in zip(starts, np.r_[starts[1:], block.size]):
        yield pix[s0:s1], wts[s0:s1]


def _crop(scene: LayerScene, img: np.ndarray, affine: np.ndarray | None = None) -> np.ndarray:
    """The frame out of a canvas image; with ``affine`` (frame px of sharp -> view px) the views' content moved."""
    W, H = scene.size
    p = scene.pad
    if affine is None:
        return np.ascontiguousarray(img[p : p + H, p : p + W])
    inv = cv2.invertAffineTransform(affine)  # view px -> sharp's frame px
    inv[:, 2] += p  # -> canvas px
    return cv2.warpAffine(img, inv, (W, H), flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)


def render_views(scene: LayerScene, lens: Lens, effects: Effects) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free (H, W, 3) float32 left and right views with ``effects`` planted (noise aside)."""
    imgs = composite(scene, lens, effects, (LEFT, RIGHT))
    M = misregistration_matrix(effects, scene.size)
    left, right = _crop(scene, imgs[LEFT], M), _crop(scene, imgs[RIGHT], M)
    gains = lr_gains(effects, scene.size)
    if gains is not None:
        left *= gains[0][..., None]
        right *= gains[1][..., None]
    return left, right


def render_sharp(scene: LayerScene, lens: Lens, effects: Effects, sharp_f_number: float = 22.0) -> np.ndarray:
    """Noise-free (H, W, 3) float32 ``sharp``: the full pupil at ``sharp_f_number`` through the same lens (its focus
    error, colour and aberrations scaled to that aperture; no DP effect), or the all-in-focus radiance (0)."""
    if sharp_f_number == 0:
        return scene.radiance()
    small = Lens(lens.focal_length_mm, float(sharp_f_number), lens.focus_distance_mm, lens.pixel_pitch_mm)
    return _crop(scene, composite(scene, small, effects, (FULL,), dual_pixel=False)[FULL])


# ---------------------------------------------------------------------------------------------------- sensor
def views_noise(effects: Effects, shot_var: float = NOMINAL_SHOT_VAR, read_sigma: float = NOMINAL_READ_SIGMA
                ) -> tuple[float, float]:
    """The views' (shot variance, read sigma): nominal, or raised by ``noise`` (exposure 1 + a times shorter)."""
    a = effects.get("noise")
    return shot_var * (1.0 + a), read_sigma * (1.0 + a)


def noise_ratio(strength: float, intensity: float = 0.25) -> float:
    """The views' noise variance over the nominal at ``intensity`` with ``noise`` at ``strength`` (x its default)."""
    shot, read = views_noise(Effects.of({"noise": strength} if strength else "none"))
    return (shot * intensity + read * read) / (NOMINAL_SHOT_VAR * intensity + NOMINAL_READ_SIGMA**2)


def add_sensor_noise(rng: np.random.Generator, img: np.ndarray, shot_var: float, read_sigma: float) -> np.ndarray:
    """``img`` plus Gaussian noise of variance ``shot_var * I + read_sigma^2`` per pixel and channel (linear)."""
    var = shot_var * np.clip(img, 0.0, None) + read_sigma * read_sigma
    return (img + rng.standard_normal(img.shape) * np.sqrt(var)).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- writer
def canvas_pad(size: tuple[int, int]) -> int:
    """Canvas margin (px) of the scenes: covers the widest blur radius the scenes reach (25 px of CoC at 256 px),
    with the effects up to about 3 x their defaults."""
    return int(math.ceil(0.12 * size[0])) + 6


def _required_pad(lens_fmin: Lens, effects: Effects, size: tuple[int, int], c_max_px: float) -> float:
    """The canvas margin (px) ``effects`` need at the widest aperture: the largest blur radius of the scenes' CoCs up
    to ``c_max_px`` grown by the focus error and colour, the aberrations' extra reach, the misregistration."""
    o = optics_of(lens_fmin, effects)
    shifts_mm = abs(effects.get("focus_offset")) + abs(effects.get("chromatic_defocus"))  # of the image (CoC growth)
    grow = lens_fmin.aperture_mm * shifts_mm / lens_fmin.sensor_distance_mm() / lens_fmin.pixel_pitch_mm
    reach = 0.5 * (c_max_px + grow) + 0.6 * (abs(o.sa3_px) + abs(o.sa5_px)) + 0.5 * o.astig_px * 1.6
    M = misregistration_matrix(effects, size)
    mis = 0.0 if M is None else float(np.abs(M[:, 2]).max() + 0.01 * size[0])
    return reach + mis + 2


def _splits(n_scenes: int) -> list[str]:
    """Split of each scene: the last ``k`` test, the ``k`` before val, the rest train (k = max(1, n // 6))."""
    if n_scenes < 3:
        raise ValueError(f"scenes={n_scenes}: train, val and test need at least 3 scenes")
    k = max(1, n_scenes // 6)
    return ["test" if i >= n_scenes - k else ("val" if i >= n_scenes - 2 * k else "train") for i in range(n_scenes)]


def _png16(path: Path, img: np.ndarray) -> None:
    v = np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)
    if not cv2.imwrite(str(path), np.ascontiguousarray(v[..., ::-1]) if v.ndim == 3 else v):
        raise OSError(f"could not write {path}")


def write_dataset(
    out: str | Path,
    effects: str | Sequence[str] | Mapping[str, float] | None = "none",
    strength: float = 1.0,
    *,
    scenes: int = 12,
    size: tuple[int, int] = (256, 170),
    f_numbers: tuple[float, ...] = (2.0, 4.0),
    seed: int = 0,
    noise: bool = True,
    shot_var: float = NOMINAL_SHOT_VAR,
    read_sigma: float = NOMINAL_READ_SIGMA,
    sharp_f_number: float = 22.0,
    focal_length_mm: float = 85.0,
    sensor_width_mm: float = 36.0,
) -> dict[str, list[str]]:
    """Write a format-v1 dataset of ``scenes`` x ``f_numbers`` pairs with ``effects`` planted; returns the splits.

    ``effects``: see :meth:`Effects.of` (magnitudes :data:`EFFECT_DEFAULTS` x ``strength``). ``noise`` False leaves
    every image noise-free; otherwise the views get ``(shot_var, read_sigma)`` (raised by ``noise``) and ``sharp``
    the nominal noise. ``sharp`` is rendered at ``sharp_f_number`` (0 = all-in-focus), stated in params.json.
    Splits by scene (:func:`_splits`). ``planted.json`` at the root records what was planted. The dataset is written
    into a hidden temporary folder and renamed into place; an existing ``out`` is an error (never overwritten).
    """
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out}: already exists; pupil_dp.write_dataset never overwrites a dataset")
    eff = Effects.of(effects, strength)
    W, H = size
    pitch = sensor_width_mm / W
    labels = _splits(scenes)
    pad = canvas_pad(size)
    f_min = float(min(f_numbers))
    need = _required_pad(Lens(focal_length_mm, f_min, 900.0, pitch), eff, size, 25.0 * W / REFERENCE_WIDTH_PX)
    if need > pad:
        raise ValueError(f"effects too strong for the scenes' canvas margin ({need:.1f} px > {pad} px)")
    view_noise = views_noise(eff, shot_var, read_sigma)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    ss = np.random.SeedSequence([int(seed), 0x70757069])
    scene_seeds = ss.spawn(scenes)
    try:
        for si, split in enumerate(labels):
            srng, nseed = (np.random.default_rng(s) for s in scene_seeds[si].spawn(2))
            scene = layer_scene(srng, size, pad, focal_length_mm, f_min, pitch)
            depth = scene.depth_mm()
            F = scene.focus_mm
            fx, fy = scene.focus_px
            depth_png = np.clip(np.round(depth), 1, 65535).astype(np.uint16)
            for N in f_numbers:
                lens = Lens(focal_length_mm, float(N), F, pitch)
                left, right = render_views(scene, lens, eff)
                sharp = render_sharp(scene, lens, eff, sharp_f_number)
                if noise:
                    left = add_sensor_noise(nseed, left, *view_noise)
                    right = add_sensor_noise(nseed, right, *view_noise)
                    sharp = add_sensor_noise(nseed, sharp, shot_var, read_sigma)
                scene_id = f"pu{seed}-{si:02d}"
                pid = f"{scene_id}_pu_f{N:g}"
                d = tmp / "pairs" / pid
                d.mkdir(parents=True)
                _png16(d / "sharp.png", sharp)
                _png16(d / "left.png", left)
                _png16(d / "right.png", right)
                if not cv2.imwrite(str(d / "depth.png"), depth_png):
                    raise OSError(f"could not write {d / 'depth.png'}")
                tifffile.imwrite(d / "depth.tif", depth.astype(np.float32))
                tifffile.imwrite(d / "coc.tif", lens.coc_px(depth).astype(np.float32))
                params = {"pair_id": pid, "scene": scene_id, "camera": "pu", "f_number": float(N),
                          "focus_distance_mm": float(F), "focal_length_mm": float(focal_length_mm),
                          "pixel_pitch_mm": float(pitch), "focus_point_px": [int(fx), int(fy)], "image_size": [W, H],
                          "sharp_f_number": float(sharp_f_number)}
                (d / "params.json").write_text(json.dumps(params, indent=1))
                splits[split].append(pid)
        index = {"format": "dp5k-dataset", "version": 1, "splits": splits, "generator": "dp5k_testing.pupil_dp"}
        (tmp / "dataset.json").write_text(json.dumps(index, indent=1))
        planted = {"generator": "dp5k_testing.pupil_dp", "effects": eff.a, "strength": strength, "seed": seed,
                   "noise": noise, "nominal_noise": {"shot_var": shot_var, "read_sigma": read_sigma},
                   "views_noise": {"shot_var": view_noise[0], "read_sigma": view_noise[1]},
                   "sharp_f_number": float(sharp_f_number),
                   "units": {k: v for k, v in _UNITS.items() if k in eff.a},
                   "note": "what was planted, for benchmarks; dp5k diagnose never reads this file"}
        (tmp / "planted.json").write_text(json.dumps(planted, indent=1))
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return splits


_UNITS = {
    "lr_gain_imbalance": "gain ramp amplitude (1)",
    "field_varying_psf": "astigmatic CoC split at the corners at f/2 (mm on the sensor)",
    "chromatic_defocus": "blue's image distance behind green's (mm; red 0.55 x)",
    "disparity_scale": "half width of the photodiodes' soft split (tan of the ray angle)",
    "focus_offset": "back-focus error (mm on the sensor; > 0 focuses nearer)",
    "psf_profile": "angular-acceptance exponent at the rim at f/2",
    "front_back_asymmetry": "third-order spherical ray aberration at f/2 (mm on the sensor)",
    "misregistration": "similarity scale factor (shift 0.65 px, 0.05 deg, 0.12 % at 1)",
    "noise": "exposure shortening minus 1 (shot variance and read sigma x (1 + a))",
}


def write_matrix_cell(out: str | Path, effects: str | Sequence[str] | Mapping[str, float] | None, strength: float = 1.0,
                      seed: int = 0, size: tuple[int, int] = (128, 86), pairs: int = 8) -> Path:
    """One small confusion-matrix cell: ``pairs`` pairs (at least 3 scenes x f/2, f/4) at ``size``. Returns ``out``."""
    write_dataset(out, effects, strength, scenes=max(3, pairs // 2), size=size, seed=seed)
    return Path(out)
