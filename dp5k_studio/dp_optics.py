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
SMALL_LIMIT_PX = 4.0
GEOM_STEP = 0.08
LOWRES_RADIUS_PX = 8.0


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
    if s_field > 0:
        xn, yn = field_coords(H, W)
        out *= (1.0 + 0.30 * s_field * (xn**2 + yn**2) / 2.0)[:, :, None]
    s_fb = eff.s("front_back_asymmetry")
    if s_fb > 0:
        out = np.where(out < 0, out * (1.0 + 0.10 * s_fb), out).astype(np.float32)
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
    if s_prof > 0:
        w = w * (1.0 + 1.5 * s_prof * rho**4)
    s_fb = eff.s("front_back_asymmetry")
    if s_fb > 0:
        w = w * ((1.0 + s_fb * rho**2) if c > 0 else (1.0 + s_fb * (1.0 - rho**2)))
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
OCCLUDE_REL = 0.25


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
    in ``c``, so the blend's DP centroid (proportional to ``c`` for each disc) is exact."""
    c = np.asarray(key, dtype=np.float64)
    k = np.floor(_layer_coord(c)).astype(np.int64)
    c0, c1 = _layer_coc(k), _layer_coc(k + 1)
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
    """Render the two DP views of a sharp radiance image with depth.

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
    eff = effects or EffectSet()
    img = np.ascontiguousarray(radiance, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise BadInputError(f"radiance must be (H, W, 3), got {img.shape}")
    H, W = img.shape[:2]
    if np.shape(depth_mm) != (H, W):
        raise BadInputError(f"depth shape {np.shape(depth_mm)} differs from image {(H, W)}")
    z = np.asarray(depth_mm, dtype=np.float64)
    coc_out = coc_channels_px(z, lens, eff)
    # the camera sees beyond the frame: extend the scene by mirroring (so the border is not dark and
    # every view is normalized alike), render, crop back
    P = min(int(math.ceil(float(np.abs(coc_out).max()) / 2.0)) + 2, H - 1, W - 1)
    pad2 = lambda a: np.pad(a, ((P, P), (P, P)) + ((0, 0),) * (a.ndim - 2), mode="symmetric")  # noqa: E731
    img = pad2(img)
    z = pad2(z)
    coc = pad2(coc_out)
    H, W = img.shape[:2]
    zsort = np.where(np.isfinite(z) & (z > 0), z, lens.focus_distance_mm)
    # hidden surfaces (second hits behind the visible one), when the caller knows them
    h_img = h_flat = None
    n_front = H * W
    src_z, src_c = zsort.ravel(), coc.reshape(-1, 3)
    if hidden is not None:
        h_rad, h_depth = hidden
        if np.shape(h_rad) != (H - 2 * P, W - 2 * P, 3) or np.shape(h_depth) != (H - 2 * P, W - 2 * P):
            raise BadInputError("hidden radiance/depth must match the image's shape")
        hz = pad2(np.asarray(h_depth, dtype=np.float64))
        ok = np.isfinite(hz) & (hz > 0)
        h_coc = pad2(coc_channels_px(np.where(ok[P:H - P, P:W - P], hz[P:H - P, P:W - P], np.nan), lens, eff))
        cf, chd = coc[:, :, 1], h_coc[:, :, 1]
        ok &= (hz > zsort) & ((chd - cf) > np.maximum(OCCLUDE_MIN_PX, OCCLUDE_REL * np.maximum(np.abs(cf), np.abs(chd))))
        # a hidden surface can only show within the front surface's blur radius of its silhouette
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
        h_img = pad2(np.asarray(h_rad, dtype=np.float32))
        # sources: front pixels 0 .. n_front - 1, then hidden ones (n_front + i is hidden pixel h_flat[i])
        src_z = np.concatenate([src_z, hz.ravel()[h_flat]])
        src_c = np.concatenate([src_c, h_coc.reshape(-1, 3)[h_flat]])
    # each source's light is split between the two CoC bins that bracket it, so blur varies continuously
    # along a slanted surface (one bin per pixel made its blur a staircase: 2-4e-3 rms error against an exact
    # per-pixel superposition on slanted planes, as large as the planted effects; split, 1e-4)
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
    # source entries of every layer, grouped once by sorting
    order = np.argsort(inv_all, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    halves = ["L", "R"] + (["F"] if full else [])
    acc = {h: np.zeros((H, W, 3), np.float32) for h in halves}
    cov_acc = {h: np.zeros((H, W, 3), np.float32) for h in halves}
    chroma = effects is not None and eff.s("chromatic_defocus") > 0
    nT = 3 if chroma else 1  # one transmittance for all colours unless their kernels differ
    T = {h: np.ones((H, W, nT), np.float32) for h in halves}
    pending: dict[str, list] = {}
    for li in np.argsort(zmean, kind="stable"):
        members = order[starts[li] : starts[li + 1]]
        src = all_src[members]
        wt = all_w[members].astype(np.float32)
        is_front = src < n_front
        front_flat, w_front = src[is_front], wt[is_front]
        hidden_flat = h_flat[src[~is_front] - n_front] if h_flat is not None else src[:0]
        w_hidden = wt[~is_front]
        flat_all = np.concatenate([front_flat, hidden_flat])
        rr, cc = flat_all // W, flat_all % W
        c3 = cmean[li]
        R = float(np.max(np.abs(c3))) / 2.0
        s = 1
        while R / (2 * s) >= LOWRES_RADIUS_PX:
            s *= 2
        pad = int(math.ceil(R)) + 3
        y0, y1 = max(0, int(rr.min()) - pad), min(H, int(rr.max()) + 1 + pad)
        x0, x1 = max(0, int(cc.min()) - pad), min(W, int(cc.max()) + 1 + pad)
        h, w = y1 - y0, x1 - x0
        alpha = np.zeros((h, w), np.float32)
        color = np.zeros((h, w, 3), np.float32)
        fr, fc = front_flat // W - y0, front_flat % W - x0
        alpha[fr, fc] = w_front
        color[fr, fc] = w_front[:, None] * img[front_flat // W, front_flat % W]
        if hidden_flat.size:  # a hidden surface is >= 2 px of CoC behind the front one: never in its bins
            hr, hc = hidden_flat // W - y0, hidden_flat % W - x0
            alpha[hr, hc] = w_hidden
            color[hr, hc] = w_hidden[:, None] * h_img[hidden_flat // W, hidden_flat % W]
        if s > 1:
            hp, wp = -(-h // s) * s, -(-w // s) * s
            alpha_p = np.zeros((hp, wp), np.float32)
            alpha_p[:h, :w] = alpha
            color_p = np.zeros((hp, wp, 3), np.float32)
            color_p[:h, :w] = color
            alpha_l, color_l = _pyr_down(alpha_p, s), _pyr_down(color_p, s)
        else:
            alpha_l, color_l = alpha, color
        kern = [left_kernel(c3[ch] / s, eff) for ch in range(3)]
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
            # nearer layers whose blur is close to this one's are the same surface continued, not
            # occluders: they join the transmittance, as one group, once a layer clearly behind comes
            waiting = pending.setdefault(hname, [])
            c_here = float(c3[1])
            group = [p for p in waiting if _occludes(p[0], c_here)]
            if group:
                _commit(T[hname], group)
                waiting = [p for p in waiting if not _occludes(p[0], c_here)]
            Tv = T[hname][y0:y1, x0:x1]
            acc[hname][y0:y1, x0:x1] += Tv * bc
            cov_acc[hname][y0:y1, x0:x1] += Tv * ba
            waiting.append((c_here, y0, y1, x0, x1, ba))
            pending[hname] = waiting
    out = {}
    crop = (slice(P, H - P), slice(P, W - P))
    for hname in halves:
        out[hname] = acc[hname][crop] / np.maximum(cov_acc[hname][crop], 1e-6)
    left = 0.5 * out["L"]
    right = 0.5 * out["R"]
    if view_effects:
        left, right = apply_view_effects(left, right, eff)
    return DPRender(left.astype(np.float32), right.astype(np.float32), out.get("F"), coc_out)


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
    if s_f > 0:
        k_rl = k_rl + 0.25 * s_f * np.maximum(0.0, -xn)
        k_lr = k_lr + 0.25 * s_f * np.maximum(0.0, xn)
    if kap > 0 or s_f > 0:
        k_rl = np.minimum(k_rl, 0.5)[:, :, None]
        k_lr = np.minimum(k_lr, 0.5)[:, :, None]
        left, right = left * (1 - k_lr) + right * k_rl, right * (1 - k_rl) + left * k_lr
    s_g = effects.s("lr_gain_imbalance")
    if s_g > 0:
        log_rho = s_g * (0.18 + 0.10 * xn - 0.06 * yn**2)
        rho = np.exp(log_rho)[:, :, None]
        left = left * (2.0 * rho / (1.0 + rho))
        right = right * (2.0 / (1.0 + rho))
    s_m = effects.s("misregistration")
    if s_m > 0:
        dx, dy = 0.0030 * s_m * W, -0.0015 * s_m * H
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
