r"""Dual-pixel image formation: thin lens, half-aperture PSFs, occlusion-aware layered compositing.

Model (paper Eq. 1, 2, 6). A scene point at depth ``z`` images, through a thin lens of focal length ``f``
and aperture diameter ``A = f / N`` focused at ``F`` (sensor at ``v = 1/(1/f - 1/F)``), into a disc of signed
diameter

.. math::  C = A \frac{v - v_z}{v_z}, \qquad v_z = \frac{1}{1/f - 1/z}

on the sensor, which equals Eq. 6, ``f^2 (z - F) / (N z (F - f))``, for one focal length; the chromatic
effect gives each colour its own ``f``. ``C > 0`` behind focus. The left photodiode integrates the half of
the aperture whose light lands on the left half of the disc when ``C > 0`` (and on the right half when
``C < 0``); the right PSF is the hflip of the left one; each is normalized to 1 and the views are
``I_l = H_l * I_s / 2``, ``I_r = H_r * I_s / 2`` (Eq. 2).

Occlusion. The image is sliced into depth layers by signed CoC (uniform 0.5 px steps up to |C| = 4 px,
then geometric steps of 8 %); each pixel's light is split between the two bins that bracket its CoC
(weights linear in C) and each bin is blurred with its own CoC, so blur varies continuously along
a slanted surface (within 1-5e-4 rms of an exact per-pixel superposition). Layers are composited front to back with the
"over" operator on blurred alpha, separately for each aperture half, and normalized by the accumulated
coverage:

.. math::  O = \frac{\sum_k T_k (H_k * \alpha_k I)}{\sum_k T_k (H_k * \alpha_k)}, \qquad
           T_k = \prod_{groups\ G} \mathrm{clip}(1 - \sum_{j \in G} H_j * \alpha_j, 0, 1)

where a layer is only occluded by nearer layers whose blur clearly differs from its own
(``C_k - C_j > max(2 px, 0.25 max(|C_j|, |C_k|))``): nearer layers of nearly the same blur are the same
continuous surface cut into bins (occluding them would draw seams), or so close in depth that occlusion
changes nothing visible. Layers that start occluding together form one group ``G`` whose alphas add, so
the seams between the bins of one surface stay opaque to what lies behind;

so a blurred foreground spills over the background but a blurred background never spills over a sharp
foreground. Layers whose blur radius exceeds 16 px are blurred at a 2^k-times reduced resolution through
a Gaussian pyramid (radius 8..16 px there; pyrDown/pyrUp keep every feature's centroid, so DP disparity
stays exact and the added variance is under 2 % of the disc's), which keeps a 1680 x 1120 pair within
seconds. In regions without occlusion
``left + right`` equals the full-aperture render exactly (Eq. 2); at occlusion edges the two halves are
composited separately (each sees its own occlusion), which the full-aperture composite approximates.

PSF kernels are built by splatting a fixed low-discrepancy (sunflower) set of points of the unit disc,
scaled to the radius, bilinearly into a pixel grid: this keeps the centroid and energy exact at every
size, including sub-pixel discs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError

from .effects import EffectSet, effect_parameters

F32 = NDArray[np.float32]

_N_DISC = 6144
_GOLDEN = math.pi * (3.0 - math.sqrt(5.0))
_i = np.arange(_N_DISC) + 0.5
_DISC_R = np.sqrt(_i / _N_DISC)
_DISC_XY = np.stack([_DISC_R * np.cos(_i * _GOLDEN), _DISC_R * np.sin(_i * _GOLDEN)], axis=1)
"""(N, 2) unit-disc sample points (x right, y down), uniform in area."""

SMALL_STEP_PX = 0.5
"""Depth layers are 0.5 px of signed CoC apart up to :data:`SMALL_LIMIT_PX` ..."""
SMALL_LIMIT_PX = 4.0
GEOM_STEP = 0.08
"""... and 8 % of |CoC| apart beyond it (:func:`_layer_coord`)."""
LOWRES_RADIUS_PX = 8.0
"""Layers whose blur radius reaches twice this (px) are blurred on a Gaussian pyramid level where it is
8..16 px (:func:`_pyramid_factor`)."""


@dataclass(frozen=True)
class LensSetting:
    """One exposure's optics.

    Attributes:
        focal_length_mm: thin-lens focal length ``f`` (mm).
        f_number: ``N``.
        focus_distance_mm: the distance the lens is *truly* focused at (mm) (focus_offset applied).
        pixel_pitch_mm: pixel pitch of the image being rendered (mm).
    """

    focal_length_mm: float
    f_number: float
    focus_distance_mm: float
    pixel_pitch_mm: float

    def __post_init__(self) -> None:
        if not (self.f_number > 0 and self.pixel_pitch_mm > 0 and self.focus_distance_mm > self.focal_length_mm > 0):
            raise BadInputError(f"invalid lens setting {self}")


def field_coords(H: int, W: int) -> tuple[F32, F32]:
    """Normalized field coordinates ``x_n, y_n`` in [-1, 1] (pixel centres), shapes (1, W) and (H, 1)."""
    xn = ((np.arange(W, dtype=np.float32) + 0.5) / W * 2.0 - 1.0)[None, :]
    yn = ((np.arange(H, dtype=np.float32) + 0.5) / H * 2.0 - 1.0)[:, None]
    return xn, yn


def coc_channels_px(depth_mm: NDArray[np.floating], lens: LensSetting, effects: EffectSet | None = None) -> F32:
    """Effective signed CoC diameter per colour channel, in px of the rendered image.

    Args:
        depth_mm: (H, W) z-depth in mm; <= 0 or non-finite = unknown (rendered in focus, CoC 0).
        lens: the optics (``focus_distance_mm`` is the true focus).
        effects: chromatic_defocus, field_varying_psf and front_back_asymmetry change it.

    Returns:
        (H, W, 3) float32 signed CoC diameters (R, G, B) in px.
    """
    eff = effects or EffectSet()
    z = np.asarray(depth_mm, dtype=np.float64)
    ok = np.isfinite(z) & (z > 0)
    z = np.where(ok, z, lens.focus_distance_mm)
    f = lens.focal_length_mm
    A = f / lens.f_number
    v = 1.0 / (1.0 / f - 1.0 / lens.focus_distance_mm)
    shifts = effect_parameters("chromatic_defocus", eff.s("chromatic_defocus"))["focal_shift_mm_rgb"]
    H, W = z.shape
    out = np.empty((H, W, 3), np.float32)
    for ch in range(3):
        if ch > 0 and shifts[ch] == shifts[ch - 1]:
            out[:, :, ch] = out[:, :, ch - 1]
            continue
        fc = f + shifts[ch]
        vz = 1.0 / (1.0 / fc - 1.0 / z)
        out[:, :, ch] = np.where(ok, A * (v - vz) / vz / lens.pixel_pitch_mm, 0.0)
    s_field = eff.s("field_varying_psf")
    if s_field > 0:  # the disc grows with the squared field radius (corner = 1)
        growth = effect_parameters("field_varying_psf", s_field)["coc_growth_at_corner"]
        xn, yn = field_coords(H, W)
        out *= (1.0 + growth * (xn**2 + yn**2) / 2.0)[:, :, None]
    s_fb = eff.s("front_back_asymmetry")
    if s_fb > 0:  # discs in front of focus are larger
        front = effect_parameters("front_back_asymmetry", s_fb)["front_size_factor"]
        out = np.where(out < 0, out * front, out).astype(np.float32)
    return out


def left_kernel(coc_px: float, effects: EffectSet | None = None) -> F32:
    """The left-view PSF ``H_l`` for a signed CoC diameter (px): odd square, sums to 1, centred.

    For ``coc_px > 0`` the mass lies on the left half of the disc (x < 0), for ``coc_px < 0`` on the right
    half. The right PSF is ``left_kernel(c)[:, ::-1]`` (hflip). psf_profile and front_back_asymmetry
    reshape the radial profile.
    """
    eff = effects or EffectSet()
    c = float(coc_px)
    R = abs(c) / 2.0
    half = int(math.ceil(R)) + 1
    size = 2 * half + 1
    pts = _DISC_XY * R
    rho = _DISC_R
    w = np.ones(_N_DISC)
    s_prof = eff.s("psf_profile")
    if s_prof > 0:  # brighter rim: weight 1 + g rho^p
        prof = effect_parameters("psf_profile", s_prof)
        w = w * (1.0 + prof["rim_gain"] * rho ** prof["rim_power"])
    s_fb = eff.s("front_back_asymmetry")
    if s_fb > 0:  # behind focus a brighter rim, in front a brighter centre
        fb = effect_parameters("front_back_asymmetry", s_fb)
        w = w * ((1.0 + fb["back_rim_gain"] * rho**2) if c > 0 else (1.0 + fb["front_center_gain"] * (1.0 - rho**2)))
    if c > 0:
        sel = pts[:, 0] < 0
    elif c < 0:
        sel = pts[:, 0] > 0
    else:
        sel = np.ones(_N_DISC, bool)
    # left half's mass (mirror the point set so that L and R have exactly mirrored samples)
    p = pts[sel]
    wt = w[sel]
    x = p[:, 0] + half
    y = p[:, 1] + half
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = x - x0
    fy = y - y0
    k = np.zeros(size * size)
    for dy, dx, ww in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(k, (y0 + dy) * size + (x0 + dx), wt * ww)
    k = k.reshape(size, size)
    # vertical symmetry of a symmetric lens: symmetrize about the horizontal axis
    k = 0.5 * (k + k[::-1, :])
    return (k / k.sum()).astype(np.float32)


def _conv(img: F32, psf: F32) -> F32:
    """True convolution (light spreading) of a 2D image with an odd PSF, zero outside."""
    return cv2.filter2D(img, cv2.CV_32F, psf[::-1, ::-1].copy(), borderType=cv2.BORDER_CONSTANT)


def _pyr_down(a: F32, s: int) -> F32:
    """Gaussian-pyramid reduction by ``s`` (a power of 2): centroid-preserving (binomial 5-tap), sizes must divide."""
    while s > 1:
        a = cv2.pyrDown(a, dstsize=(a.shape[1] // 2, a.shape[0] // 2))
        s //= 2
    return a


def _pyr_up(a: F32, s: int) -> F32:
    """Gaussian-pyramid expansion by ``s`` (inverse alignment of :func:`_pyr_down`)."""
    while s > 1:
        a = cv2.pyrUp(a, dstsize=(a.shape[1] * 2, a.shape[0] * 2))
        s //= 2
    return a


OCCLUDE_MIN_PX = 2.0
"""A layer occludes a farther one only when their signed CoCs differ by more than this (px) ..."""
OCCLUDE_REL = 0.25
"""... and by more than this fraction of the larger |CoC| (:func:`_occludes`)."""
MAX_CROSSTALK = 0.5
"""At most half of a photodiode's light can cross to the other: at 0.5 both views are the same image."""


def _occludes(c_near_px: float, c_far_px: float) -> bool:
    """Whether a layer of signed CoC ``c_near`` occludes one of ``c_far`` (behind it): their blurs must
    differ by more than ``max(2 px, 25 %)``; closer layers are the same surface continued, or so close in
    depth that occlusion changes nothing visible."""
    return (c_far_px - c_near_px) > max(OCCLUDE_MIN_PX, OCCLUDE_REL * max(abs(c_near_px), abs(c_far_px)))


def _commit(T: F32, group: list[tuple]) -> None:
    """Multiply a group of pending layers into the transmittance ``T``: as one surface, their blurred
    alphas add (``T *= clip(1 - sum(alpha), 0, 1)``), so seams between its depth bins stay opaque."""
    y0 = min(p[1] for p in group)
    y1 = max(p[2] for p in group)
    x0 = min(p[3] for p in group)
    x1 = max(p[4] for p in group)
    total = np.zeros((y1 - y0, x1 - x0, group[0][5].shape[2]), np.float32)
    for _, a0, a1, b0, b1, ba in group:
        total[a0 - y0 : a1 - y0, b0 - x0 : b1 - x0] += ba
    T[y0:y1, x0:x1] *= np.clip(1.0 - total, 0.0, 1.0)


def _layer_coord(key: NDArray[np.floating]) -> NDArray[np.float64]:
    """Continuous signed bin coordinate of a signed CoC (px): ``|C| / 0.5`` up to 4 px, then one unit per 8 %
    (``SMALL_STEP_PX``, ``SMALL_LIMIT_PX``, ``GEOM_STEP``); bin ``k`` sits at :func:`_layer_coc` ``(k)``."""
    a = np.abs(np.asarray(key, dtype=np.float64))
    n_small = SMALL_LIMIT_PX / SMALL_STEP_PX
    with np.errstate(divide="ignore"):
        big = n_small + np.log(np.maximum(a, 1e-9) / SMALL_LIMIT_PX) / math.log(1.0 + GEOM_STEP)
    return np.sign(key) * np.where(a <= SMALL_LIMIT_PX, a / SMALL_STEP_PX, big)


def _layer_coc(k: NDArray[np.integer]) -> NDArray[np.float64]:
    """Signed CoC (px) of bin ``k``, the inverse of :func:`_layer_coord` at integers."""
    a = np.abs(k).astype(np.float64)
    n_small = SMALL_LIMIT_PX / SMALL_STEP_PX
    return np.sign(k) * np.where(a <= n_small, a * SMALL_STEP_PX, SMALL_LIMIT_PX * (1.0 + GEOM_STEP) ** (a - n_small))


def _bin_split(key: NDArray[np.floating]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The lower of the two bins that bracket each signed CoC ``c`` and the weight of the upper one: a pixel's
    light goes ``1 - t`` to bin ``k`` and ``t`` to bin ``k + 1``, ``t = (c - c_k) / (c_{k+1} - c_k)``. Linear
    in ``c``, so the blend's DP centroid (proportional to ``c`` for each disc) is exact. The bin CoCs come from
    a table over the few bins present (one power per bin, not per pixel)."""
    c = np.asarray(key, dtype=np.float64)
    k = np.floor(_layer_coord(c)).astype(np.int64)
    lo = int(k.min()) if k.size else 0
    table = _layer_coc(np.arange(lo, (int(k.max()) if k.size else 0) + 2))
    c0, c1 = table[k - lo], table[k - lo + 1]
    return k, np.clip((c - c0) / (c1 - c0), 0.0, 1.0)


@dataclass
class DPRender:
    """Linear DP views before the sensor: ``left``/``right`` (H, W, 3) float32, each carrying half the
    light (Eq. 2); ``full`` (H, W, 3) the full-aperture composite when requested (else None);
    ``coc_px`` (H, W, 3) the effective CoC used."""

    left: F32
    right: F32
    full: F32 | None
    coc_px: F32


def render_dp(
    radiance: NDArray[np.floating],
    depth_mm: NDArray[np.floating],
    lens: LensSetting,
    effects: EffectSet | None = None,
    *,
    full: bool = False,
    view_effects: bool = True,
    hidden: tuple[NDArray[np.floating], NDArray[np.floating]] | None = None,
) -> DPRender:
    """Render the two DP views of a sharp radiance image with depth: ``plan_dp(...).render(...)``.

    Steps: the effective CoC per colour (:func:`coc_channels_px`); the light sources on a grid padded by the
    largest blur radius (:func:`_sources`); their split into CoC layers (:func:`_layers`); each layer
    splatted, blurred per aperture half and composited front to back (:func:`_composite`); the per-view
    effects (:func:`apply_view_effects`). Everything up to the splat depends on depth and lens only
    (:class:`DPPlan`); callers rendering many radiance images of one geometry (the studio's 92
    structured-light frames) keep the plan and call :meth:`DPPlan.render` per image.

    Args:
        radiance: (H, W, 3) linear sharp (pinhole) image.
        depth_mm: (H, W) z-depth in mm (<= 0 / non-finite = unknown: kept in focus).
        lens: optics; ``lens.focus_distance_mm`` is where the lens truly focuses.
        effects: planted effects (all of them act here except ``noise`` and ``focus_offset``, which the
            caller applies: the sensor adds noise and the caller chooses the true focus).
        full: also composite the full-aperture image (for the energy check and the f/22 frame).
        view_effects: apply the per-view effects (crosstalk, gains, misregistration) after compositing.
        hidden: optional ``(radiance (H, W, 3), depth_mm (H, W))`` of the surface behind the visible one
            (the studio's second ray hit; inf/0 = none). Placed in its own depth layer, it shows through
            where a blurred foreground edge lets part of the aperture see past it (partial occlusion),
            instead of the coverage-normalized guess.

    Returns:
        :class:`DPRender`.
    """
    img = np.asarray(radiance)
    if img.ndim != 3 or img.shape[2] != 3:
        raise BadInputError(f"radiance must be (H, W, 3), got {img.shape}")
    if np.shape(depth_mm) != img.shape[:2]:
        raise BadInputError(f"depth shape {np.shape(depth_mm)} differs from image {img.shape[:2]}")
    plan = plan_dp(depth_mm, lens, effects, None if hidden is None else hidden[1])
    return plan.render(img, None if hidden is None else hidden[0], full=full, view_effects=view_effects)


@dataclass
class _Sources:
    """The light sources of one render on the padded grid (``shape`` = (H, W) after padding by ``pad`` px):
    every visible pixel (source ``i < n_front`` is padded flat index ``i``), then the hidden surface's pixels
    (source ``n_front + j`` is padded flat index ``hidden_flat[j]``)."""

    hidden_flat: NDArray[np.int64] | None
    z_mm: NDArray[np.float64]
    """(n,) depth used to order layers front to back (unknown depth sorts at the focus distance)."""
    coc_px: NDArray[np.float32]
    """(n, 3) signed CoC per colour, px."""
    n_front: int
    pad: int
    shape: tuple[int, int]


def _pad_px(coc_out: F32) -> int:
    """The scene's mirror extension (px): the largest blur radius + 2 px, at most the image size - 1."""
    H0, W0 = coc_out.shape[:2]
    return min(int(math.ceil(float(np.abs(coc_out).max()) / 2.0)) + 2, H0 - 1, W0 - 1)


def _pad2(a: NDArray, P: int) -> NDArray:
    """Mirror-extend the first two axes by ``P`` px (``np.pad`` mode ``symmetric``)."""
    return np.pad(a, ((P, P), (P, P)) + ((0, 0),) * (a.ndim - 2), mode="symmetric")


def _sources(z: NDArray[np.float64], coc_out: F32, lens: LensSetting, eff: EffectSet,
             hidden_depth_mm: NDArray[np.floating] | None) -> _Sources:
    """Pad the scene by the largest blur radius + 2 px and list its light sources.

    The camera sees beyond the frame: the scene is extended by mirroring (so the border is not dark and
    every view is normalized alike); :func:`_composite` crops back. A hidden surface contributes only where
    it lies clearly behind the visible one (:func:`_occludes`' margins) and within the visible surface's blur
    radius (+ 2 px) of a depth edge, the only place a partly open aperture can see it.
    """
    H0, W0 = coc_out.shape[:2]
    P = _pad_px(coc_out)
    z, coc = _pad2(z, P), _pad2(coc_out, P)
    H, W = z.shape
    zsort = np.where(np.isfinite(z) & (z > 0), z, lens.focus_distance_mm)
    src_z, src_c = zsort.ravel(), coc.reshape(-1, 3)
    if hidden_depth_mm is None:
        return _Sources(None, src_z, src_c, H * W, P, (H, W))
    if np.shape(hidden_depth_mm) != (H0, W0):
        raise BadInputError("hidden radiance/depth must match the image's shape")
    hz = _pad2(np.asarray(hidden_depth_mm, dtype=np.float64), P)
    ok = np.isfinite(hz) & (hz > 0)
    h_coc = _pad2(coc_channels_px(np.where(ok[P:H - P, P:W - P], hz[P:H - P, P:W - P], np.nan), lens, eff), P)
    cf, chd = coc[:, :, 1], h_coc[:, :, 1]
    ok &= (hz > zsort) & ((chd - cf) > np.maximum(OCCLUDE_MIN_PX, OCCLUDE_REL * np.maximum(np.abs(cf), np.abs(chd))))
    jump = np.zeros(cf.shape, bool)
    dx = np.abs(np.diff(cf, axis=1)) > OCCLUDE_MIN_PX
    dy = np.abs(np.diff(cf, axis=0)) > OCCLUDE_MIN_PX
    jump[:, 1:] |= dx
    jump[:, :-1] |= dx
    jump[1:, :] |= dy
    jump[:-1, :] |= dy
    dist = cv2.distanceTransform((~jump).astype(np.uint8), cv2.DIST_L2, 3)
    ok &= dist <= np.abs(cf) / 2.0 + 2.0
    h_flat = np.nonzero(ok.ravel())[0]
    return _Sources(h_flat, np.concatenate([src_z, hz.ravel()[h_flat]]),
                    np.concatenate([src_c, h_coc.reshape(-1, 3)[h_flat]]), H * W, P, (H, W))


@dataclass
class _Layers:
    """Sources grouped into CoC layers: layer ``li`` holds the entries ``order[starts[li]:starts[li + 1]]`` of
    ``src`` (source index) and ``weight`` (its share of the source's light); ``z_mm`` (L,) is its weighted
    depth, ``coc_px`` (L, 3) its CoC per colour."""

    src: NDArray[np.int64]
    weight: NDArray[np.float64]
    order: NDArray[np.int64]
    starts: NDArray[np.int64]
    z_mm: NDArray[np.float64]
    coc_px: NDArray[np.float64]


def _layers(sources: _Sources) -> _Layers:
    """Split each source's light between the two CoC bins that bracket it (:func:`_bin_split`), so blur varies
    continuously along a slanted surface (one bin per pixel made its blur a staircase: 2-4e-3 rms error
    against an exact per-pixel superposition on slanted planes, as large as the planted effects; split,
    1e-4), and group the entries by bin."""
    src_z, src_c = sources.z_mm, sources.coc_px
    k_lo, t_hi = _bin_split(src_c[:, 1])
    all_lid = np.concatenate([k_lo, k_lo + 1])
    all_w = np.concatenate([1.0 - t_hi, t_hi])
    all_src = np.tile(np.arange(src_z.size), 2)
    keep = all_w > 1e-6
    all_lid, all_w, all_src = all_lid[keep], all_w[keep], all_src[keep]
    all_z = src_z[all_src]
    dc = src_c[all_src] - src_c[all_src, 1:2]  # per-channel CoC relative to green (chromatic_defocus)
    lo = int(all_lid.min())
    present = np.bincount(all_lid - lo)
    lut = np.cumsum(present > 0) - 1
    inv_all = lut[all_lid - lo].astype(np.int16 if lut[-1] < 32000 else np.int32)  # int16: numpy radix-sorts
    counts = present[present > 0]
    ids = np.nonzero(present)[0] + lo
    wsum = np.maximum(np.bincount(inv_all, weights=all_w), 1e-12)
    zmean = np.bincount(inv_all, weights=all_w * all_z) / wsum
    node = _layer_coc(ids)
    cmean = np.stack([node + np.bincount(inv_all, weights=all_w * dc[:, ch]) / wsum for ch in range(3)], 1)
    order = np.argsort(inv_all, kind="stable")  # source entries of every layer, grouped once by sorting
    starts = np.concatenate([[0], np.cumsum(counts)])
    return _Layers(all_src, all_w, order, starts, zmean, cmean)


def _pyramid_factor(radius_px: float) -> int:
    """The power of 2 that brings a blur radius under 2 x :data:`LOWRES_RADIUS_PX` (1 for small blurs)."""
    s = 1
    while radius_px / (2 * s) >= LOWRES_RADIUS_PX:
        s *= 2
    return s


@dataclass
class _LayerSplat:
    """Where one CoC layer's light sits: its box ``(y0, y1, x0, x1)`` on the padded grid (the members' bounding
    box grown by the blur radius + 3 px), the visible pixels' flat index inside the box (``front_loc``) and
    share of their light (``front_w``), the hidden surface's pixels likewise (``hidden_loc``, ``hidden_w``,
    ``hidden_src`` their flat index on the padded grid), and the layer's signed CoC per colour (px)."""

    box: tuple[int, int, int, int]
    front_loc: NDArray[np.int64]
    front_w: F32
    hidden_loc: NDArray[np.int64]
    hidden_src: NDArray[np.int64]
    hidden_w: F32
    coc_px: NDArray[np.float64]
    kernels: list[F32]
    """The left PSF per colour at the layer's pyramid level (:func:`_pyramid_factor`)."""


def _layer_splat(sources: _Sources, layers: _Layers, li: int, eff: EffectSet) -> _LayerSplat:
    """Layer ``li``'s members located in their box (see :class:`_LayerSplat`)."""
    H, W = sources.shape
    c3 = layers.coc_px[li]
    margin_px = int(math.ceil(float(np.max(np.abs(c3))) / 2.0)) + 3
    members = layers.order[layers.starts[li] : layers.starts[li + 1]]
    src = layers.src[members]
    wt = layers.weight[members].astype(np.float32)
    is_front = src < sources.n_front
    front_flat = src[is_front]
    hidden_flat = sources.hidden_flat[src[~is_front] - sources.n_front] if sources.hidden_flat is not None else src[:0]
    flat_all = np.concatenate([front_flat, hidden_flat])
    rr, cc = flat_all // W, flat_all % W
    y0, y1 = max(0, int(rr.min()) - margin_px), min(H, int(rr.max()) + 1 + margin_px)
    x0, x1 = max(0, int(cc.min()) - margin_px), min(W, int(cc.max()) + 1 + margin_px)
    loc = (rr - y0) * (x1 - x0) + (cc - x0)
    nf = front_flat.size
    s = _pyramid_factor(float(np.max(np.abs(c3))) / 2.0)
    kernels = [left_kernel(c3[ch] / s, eff) for ch in range(3)]
    return _LayerSplat((y0, y1, x0, x1), loc[:nf], wt[is_front], loc[nf:], hidden_flat, wt[~is_front], c3, kernels)


@dataclass
class DPPlan:
    """The depth-dependent part of a DP render (:func:`plan_dp`): the padded grid, the CoC layers front to
    back with their members, and the effective CoC. :meth:`render` forms the views of any radiance image of
    this depth map; the result equals :func:`render_dp` on the same inputs.

    Attributes:
        lens, effects: the optics it was planned for.
        coc_px: (H, W, 3) float32 effective signed CoC (px).
        pad: mirror extension (px); ``shape`` the padded (H, W).
        layers: :class:`_LayerSplat` per CoC layer, nearest first.
        has_hidden: whether a hidden surface takes part (then :meth:`render` needs its radiance).
        chroma: per-colour kernels (chromatic_defocus).
    """

    lens: LensSetting
    effects: EffectSet
    coc_px: F32
    pad: int
    shape: tuple[int, int]
    layers: list[_LayerSplat]
    has_hidden: bool
    chroma: bool

    def render(self, radiance: NDArray[np.floating], hidden_radiance: NDArray[np.floating] | None = None, *,
               full: bool = False, view_effects: bool = True) -> DPRender:
        """The DP views of ``radiance`` (H, W, 3) linear (and of the hidden surface's radiance (H, W, 3) when
        the plan has one); ``full`` and ``view_effects`` as in :func:`render_dp`."""
        img = np.ascontiguousarray(radiance, dtype=np.float32)
        H0, W0 = self.coc_px.shape[:2]
        if img.shape != (H0, W0, 3):
            raise BadInputError(f"radiance must be ({H0}, {W0}, 3) like the planned depth, got {img.shape}")
        hid = None
        if self.has_hidden:
            if hidden_radiance is None or np.shape(hidden_radiance) != (H0, W0, 3):
                raise BadInputError("hidden radiance/depth must match the image's shape")
            hid = _pad2(np.asarray(hidden_radiance, dtype=np.float32), self.pad).reshape(-1, 3)
        halves = ("L", "R", "F") if full else ("L", "R")
        out = _composite(self, _pad2(img, self.pad), hid, halves)
        left, right = 0.5 * out["L"], 0.5 * out["R"]
        if view_effects:
            left, right = apply_view_effects(left, right, self.effects)
        return DPRender(left.astype(np.float32), right.astype(np.float32), out.get("F"), self.coc_px)


def plan_dp(depth_mm: NDArray[np.floating], lens: LensSetting, effects: EffectSet | None = None,
            hidden_depth_mm: NDArray[np.floating] | None = None) -> DPPlan:
    """Plan the DP render of a depth map (:class:`DPPlan`): everything of :func:`render_dp` that does not
    depend on the radiance.

    Args:
        depth_mm: (H, W) z-depth in mm (<= 0 / non-finite = unknown: kept in focus).
        lens: optics (``focus_distance_mm`` the true focus).
        effects: planted effects (see :func:`render_dp`).
        hidden_depth_mm: (H, W) depth of the surface behind the visible one (mm; inf/0 = none), or None.
    """
    eff = effects or EffectSet()
    z = np.asarray(depth_mm, dtype=np.float64)
    if z.ndim != 2:
        raise BadInputError(f"depth must be (H, W), got {z.shape}")
    coc_out = coc_channels_px(z, lens, eff)
    sources = _sources(z, coc_out, lens, eff, hidden_depth_mm)
    layers = _layers(sources)
    splats = [_layer_splat(sources, layers, int(li), eff) for li in np.argsort(layers.z_mm, kind="stable")]
    chroma = effects is not None and eff.s("chromatic_defocus") > 0
    return DPPlan(lens, eff, coc_out, sources.pad, sources.shape, splats, hidden_depth_mm is not None, chroma)


def _splat(layer: _LayerSplat, img_pad: F32, hidden_pad: F32 | None) -> tuple[F32, F32]:
    """One radiance image's light in a layer's box: alpha (h, w) and premultiplied colour (h, w, 3).
    ``img_pad`` (H, W, 3) is the padded radiance, ``hidden_pad`` (H * W, 3) the padded hidden radiance."""
    y0, y1, x0, x1 = layer.box
    h, w = y1 - y0, x1 - x0
    alpha = np.zeros(h * w, np.float32)
    alpha[layer.front_loc] = layer.front_w
    color = alpha.reshape(h, w, 1) * img_pad[y0:y1, x0:x1]
    if layer.hidden_loc.size:  # a hidden surface is >= 2 px of CoC behind the front one: never in its bins
        assert hidden_pad is not None
        color.reshape(-1, 3)[layer.hidden_loc] = layer.hidden_w[:, None] * hidden_pad[layer.hidden_src]
        alpha[layer.hidden_loc] = layer.hidden_w
    return alpha.reshape(h, w), color


def _blur_layer(alpha: F32, color: F32, coc3_px: NDArray[np.float64], kern: list[F32], halves: tuple[str, ...],
                chroma: bool) -> dict[str, tuple[F32, F32]]:
    """Blur one layer's alpha (h, w) and colour (h, w, 3) with its left, right (hflip) and full (their mean)
    PSFs (``kern``: the left PSF per colour at the pyramid level), on a pyramid level for large blurs. Returns ``{half: (alpha (h, w, 1 or 3) clipped to [0, 1],
    colour (h, w, 3))}``; per-colour alphas only with ``chroma`` (kernels that differ per colour)."""
    h, w = alpha.shape
    s = _pyramid_factor(float(np.max(np.abs(coc3_px))) / 2.0)
    if s > 1:
        hp, wp = -(-h // s) * s, -(-w // s) * s
        alpha_p = np.zeros((hp, wp), np.float32)
        alpha_p[:h, :w] = alpha
        color_p = np.zeros((hp, wp, 3), np.float32)
        color_p[:h, :w] = color
        alpha_l, color_l = _pyr_down(alpha_p, s), _pyr_down(color_p, s)
    else:
        alpha_l, color_l = alpha, color
    out = {}
    for hname in halves:
        if hname == "L":
            ks = kern
        elif hname == "R":
            ks = [k[:, ::-1] for k in kern]
        else:
            ks = [0.5 * (k + k[:, ::-1]) for k in kern]
        if not chroma:
            ba = _conv(alpha_l, ks[1])[:, :, None]
            bc = _conv(color_l, ks[1])
        else:
            ba = np.dstack([_conv(alpha_l, ks[ch]) for ch in range(3)])
            bc = np.dstack([_conv(np.ascontiguousarray(color_l[:, :, ch]), ks[ch]) for ch in range(3)])
        if s > 1:
            ba = _pyr_up(ba, s)[:h, :w]
            bc = _pyr_up(bc, s)[:h, :w]
            if ba.ndim == 2:
                ba = ba[:, :, None]
        np.clip(ba, 0.0, 1.0, out=ba)
        out[hname] = (ba, bc)
    return out


def _composite(plan: DPPlan, img_pad: F32, hidden_pad: F32 | None, halves: tuple[str, ...]) -> dict[str, F32]:
    """Composite the plan's layers of one padded radiance image front to back per aperture half (module
    docstring) and crop the padding: ``{half: (H, W, 3)}``, each normalised by its accumulated coverage (a
    full-aperture PSF sums to 1)."""
    H, W = plan.shape
    nT = 3 if plan.chroma else 1  # one transmittance (and coverage) for all colours unless their kernels differ
    acc = {h: np.zeros((H, W, 3), np.float32) for h in halves}
    cov_acc = {h: np.zeros((H, W, nT), np.float32) for h in halves}
    T = {h: np.ones((H, W, nT), np.float32) for h in halves}
    opaque_yet = {h: False for h in halves}  # until a group is committed T is 1 and need not multiply
    pending: dict[str, list] = {}
    for layer in plan.layers:
        c3 = layer.coc_px
        y0, y1, x0, x1 = layer.box
        alpha, color = _splat(layer, img_pad, hidden_pad)
        for hname, (ba, bc) in _blur_layer(alpha, color, c3, layer.kernels, halves, plan.chroma).items():
            # nearer layers whose blur is close to this one's are the same surface continued, not
            # occluders: they join the transmittance, as one group, once a layer clearly behind comes
            waiting = pending.setdefault(hname, [])
            c_here = float(c3[1])
            group = [p for p in waiting if _occludes(p[0], c_here)]
            if group:
                _commit(T[hname], group)
                opaque_yet[hname] = True
                waiting = [p for p in waiting if not _occludes(p[0], c_here)]
            if opaque_yet[hname]:
                Tv = T[hname][y0:y1, x0:x1]
                acc[hname][y0:y1, x0:x1] += np.multiply(bc, Tv, out=bc)
                cov_acc[hname][y0:y1, x0:x1] += Tv * ba
            else:
                acc[hname][y0:y1, x0:x1] += bc
                cov_acc[hname][y0:y1, x0:x1] += ba
            waiting.append((c_here, y0, y1, x0, x1, ba))
            pending[hname] = waiting
    P = plan.pad
    crop = (slice(P, H - P), slice(P, W - P))
    return {hname: acc[hname][crop] / np.maximum(cov_acc[hname][crop], 1e-6) for hname in halves}


def apply_view_effects(left: F32, right: F32, effects: EffectSet) -> tuple[F32, F32]:
    """Per-view effects after image formation: photodiode crosstalk (disparity_scale, field_varying_psf's
    off-axis leak), L/R gains (lr_gain_imbalance) and the views' shift (misregistration).

    Crosstalk moves light between the photodiodes and so keeps ``left + right`` unchanged.
    """
    H, W = left.shape[:2]
    xn, yn = field_coords(H, W)
    kap = effect_parameters("disparity_scale", effects.s("disparity_scale"))["crosstalk"]
    k_rl = np.full((1, W), kap, np.float32)  # fraction of R's light moved to L
    k_lr = np.full((1, W), kap, np.float32)  # fraction of L's light moved to R
    s_f = effects.s("field_varying_psf")
    if s_f > 0:  # off-axis, light leaks towards the photodiode facing the optical axis, growing with |x|
        leak = effect_parameters("field_varying_psf", s_f)["edge_leak"]
        k_rl = k_rl + leak * np.maximum(0.0, -xn)
        k_lr = k_lr + leak * np.maximum(0.0, xn)
    if kap > 0 or s_f > 0:
        k_rl = np.minimum(k_rl, MAX_CROSSTALK)[:, :, None]
        k_lr = np.minimum(k_lr, MAX_CROSSTALK)[:, :, None]
        left, right = left * (1 - k_lr) + right * k_rl, right * (1 - k_rl) + left * k_lr
    s_g = effects.s("lr_gain_imbalance")
    if s_g > 0:  # log(L/R) = c0 + cx x_n + cyy y_n^2; left + right keeps its brightness
        c0, cx, cyy = effect_parameters("lr_gain_imbalance", s_g)["log_ratio_coeffs"]
        rho = np.exp(c0 + cx * xn + cyy * yn**2)[:, :, None]
        left = left * (2.0 * rho / (1.0 + rho))
        right = right * (2.0 / (1.0 + rho))
    s_m = effects.s("misregistration")
    if s_m > 0:  # both views shift by a fraction of the image size
        fx, fy = effect_parameters("misregistration", s_m)["shift_frac"]
        dx, dy = fx * W, fy * H
        left = fourier_shift(left, dx, dy)
        right = fourier_shift(right, dx, dy)
    return left.astype(np.float32), right.astype(np.float32)


def fourier_shift(img: F32, dx_px: float, dy_px: float) -> F32:
    """Band-limited sub-pixel shift (content moves by +dx right, +dy down); reflect-padded to avoid wrap."""
    H, W = img.shape[:2]
    p = int(math.ceil(max(abs(dx_px), abs(dy_px)))) + 8
    a = np.pad(img, ((p, p), (p, p)) + ((0, 0),) * (img.ndim - 2), mode="reflect")
    Hp, Wp = a.shape[:2]
    fy = np.fft.fftfreq(Hp)[:, None]
    fx = np.fft.rfftfreq(Wp)[None, :]
    ph = np.exp(-2j * np.pi * (fx * dx_px + fy * dy_px))
    if a.ndim == 3:
        ph = ph[:, :, None]
    spec = np.fft.rfft2(a, axes=(0, 1)) * ph
    out = np.fft.irfft2(spec, s=(Hp, Wp), axes=(0, 1))
    return out[p:p + H, p:p + W].astype(np.float32)
