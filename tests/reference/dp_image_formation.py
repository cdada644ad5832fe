"""The studio's Dual Pixel image formation, the reference: layered, occlusion-aware rendering of both DP views from
radiance and depth, with the physical effects of :mod:`dp5k_studio.effects`.

A readable version of :func:`dp5k_studio.render_dp`: every call bins the signed CoC into layers, splats each
layer's sources and blurs it with its half-aperture kernels (on a pyramid level for large CoCs), then composites
front to back. The package's version (a depth plan of :func:`dp5k_studio.dp_optics.plan_dp` computed once and
reused for every radiance image) must render the same views to float noise
(``tests/studio/test_reference_equivalence.py``). Slow by design: do not optimise it. Not a test module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError
from dp5k_studio.dp_optics import (GEOM_STEP, LOWRES_RADIUS_PX, OCCLUDE_MIN_PX, OCCLUDE_REL, SMALL_LIMIT_PX,
                                   SMALL_STEP_PX, DPRender, LensSetting, _commit, _conv, _occludes, _pyr_down,
                                   _pyr_up, apply_view_effects, coc_channels_px, left_kernel)
from dp5k_studio.effects import EffectSet

F32 = NDArray[np.float32]


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

    Steps: the effective CoC per colour (:func:`coc_channels_px`); the light sources on a grid padded by the
    largest blur radius (:func:`_sources`); their split into CoC layers (:func:`_layers`); each layer
    splatted, blurred per aperture half and composited front to back (:func:`_composite`); the per-view
    effects (:func:`apply_view_effects`).

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
    if np.shape(depth_mm) != img.shape[:2]:
        raise BadInputError(f"depth shape {np.shape(depth_mm)} differs from image {img.shape[:2]}")
    z = np.asarray(depth_mm, dtype=np.float64)
    coc_out = coc_channels_px(z, lens, eff)
    sources = _sources(img, z, coc_out, lens, eff, hidden)
    halves = ("L", "R", "F") if full else ("L", "R")
    chroma = effects is not None and eff.s("chromatic_defocus") > 0
    out = _composite(sources, _layers(sources), halves, eff, chroma)
    left, right = 0.5 * out["L"], 0.5 * out["R"]
    if view_effects:
        left, right = apply_view_effects(left, right, eff)
    return DPRender(left.astype(np.float32), right.astype(np.float32), out.get("F"), coc_out)


@dataclass
class _Sources:
    """The light sources of one render on the padded grid (``shape`` = (H, W) after padding by ``pad`` px):
    every visible pixel (source ``i < n_front`` is padded flat index ``i``), then the hidden surface's pixels
    (source ``n_front + j`` is padded flat index ``hidden_flat[j]``, radiance ``hidden_img``)."""

    img: F32
    hidden_img: F32 | None
    hidden_flat: NDArray[np.int64] | None
    z_mm: NDArray[np.float64]
    """(n,) depth used to order layers front to back (unknown depth sorts at the focus distance)."""
    coc_px: NDArray[np.float32]
    """(n, 3) signed CoC per colour, px."""
    n_front: int
    pad: int
    shape: tuple[int, int]


def _sources(img: F32, z: NDArray[np.float64], coc_out: F32, lens: LensSetting, eff: EffectSet,
             hidden: tuple[NDArray[np.floating], NDArray[np.floating]] | None) -> _Sources:
    """Pad the scene by the largest blur radius + 2 px and list its light sources.

    The camera sees beyond the frame: the scene is extended by mirroring (so the border is not dark and
    every view is normalized alike); :func:`_composite` crops back. A hidden surface contributes only where
    it lies clearly behind the visible one (:func:`_occludes`' margins) and within the visible surface's blur
    radius (+ 2 px) of a depth edge, the only place a partly open aperture can see it.
    """
    H0, W0 = img.shape[:2]
    P = min(int(math.ceil(float(np.abs(coc_out).max()) / 2.0)) + 2, H0 - 1, W0 - 1)

    def pad2(a: NDArray) -> NDArray:
        return np.pad(a, ((P, P), (P, P)) + ((0, 0),) * (a.ndim - 2), mode="symmetric")

    img, z, coc = pad2(img), pad2(z), pad2(coc_out)
    H, W = img.shape[:2]
    zsort = np.where(np.isfinite(z) & (z > 0), z, lens.focus_distance_mm)
    src_z, src_c = zsort.ravel(), coc.reshape(-1, 3)
    if hidden is None:
        return _Sources(img, None, None, src_z, src_c, H * W, P, (H, W))
    h_rad, h_depth = hidden
    if np.shape(h_rad) != (H0, W0, 3) or np.shape(h_depth) != (H0, W0):
        raise BadInputError("hidden radiance/depth must match the image's shape")
    hz = pad2(np.asarray(h_depth, dtype=np.float64))
    ok = np.isfinite(hz) & (hz > 0)
    h_coc = pad2(coc_channels_px(np.where(ok[P:H - P, P:W - P], hz[P:H - P, P:W - P], np.nan), lens, eff))
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
    return _Sources(img, pad2(np.asarray(h_rad, dtype=np.float32)), h_flat,
                    np.concatenate([src_z, hz.ravel()[h_flat]]), np.concatenate([src_c, h_coc.reshape(-1, 3)[h_flat]]),
                    H * W, P, (H, W))


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


def _splat_layer(sources: _Sources, layers: _Layers, li: int, margin_px: int) -> tuple[tuple[int, int, int, int], F32, F32]:
    """Layer ``li``'s premultiplied light on its bounding box grown by ``margin_px``:
    ``((y0, y1, x0, x1), alpha (h, w), colour (h, w, 3))``."""
    H, W = sources.shape
    members = layers.order[layers.starts[li] : layers.starts[li + 1]]
    src = layers.src[members]
    wt = layers.weight[members].astype(np.float32)
    is_front = src < sources.n_front
    front_flat, w_front = src[is_front], wt[is_front]
    hidden_flat = sources.hidden_flat[src[~is_front] - sources.n_front] if sources.hidden_flat is not None else src[:0]
    w_hidden = wt[~is_front]
    flat_all = np.concatenate([front_flat, hidden_flat])
    rr, cc = flat_all // W, flat_all % W
    y0, y1 = max(0, int(rr.min()) - margin_px), min(H, int(rr.max()) + 1 + margin_px)
    x0, x1 = max(0, int(cc.min()) - margin_px), min(W, int(cc.max()) + 1 + margin_px)
    h, w = y1 - y0, x1 - x0
    alpha = np.zeros((h, w), np.float32)
    color = np.zeros((h, w, 3), np.float32)
    fr, fc = front_flat // W - y0, front_flat % W - x0
    alpha[fr, fc] = w_front
    color[fr, fc] = w_front[:, None] * sources.img[front_flat // W, front_flat % W]
    if hidden_flat.size:  # a hidden surface is >= 2 px of CoC behind the front one: never in its bins
        assert sources.hidden_img is not None
        hr, hc = hidden_flat // W - y0, hidden_flat % W - x0
        alpha[hr, hc] = w_hidden
        color[hr, hc] = w_hidden[:, None] * sources.hidden_img[hidden_flat // W, hidden_flat % W]
    return (y0, y1, x0, x1), alpha, color


def _blur_layer(alpha: F32, color: F32, coc3_px: NDArray[np.float64], halves: tuple[str, ...], eff: EffectSet,
                chroma: bool) -> dict[str, tuple[F32, F32]]:
    """Blur one layer's alpha (h, w) and colour (h, w, 3) with its left, right (hflip) and full (their mean)
    PSFs, on a pyramid level for large blurs. Returns ``{half: (alpha (h, w, 1 or 3) clipped to [0, 1],
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
    kern = [left_kernel(coc3_px[ch] / s, eff) for ch in range(3)]
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


def _composite(sources: _Sources, layers: _Layers, halves: tuple[str, ...], eff: EffectSet, chroma: bool) -> dict[str, F32]:
    """Composite the layers front to back per aperture half (module docstring) and crop the padding:
    ``{half: (H, W, 3)}``, each normalised by its accumulated coverage (a full-aperture PSF sums to 1)."""
    H, W = sources.shape
    acc = {h: np.zeros((H, W, 3), np.float32) for h in halves}
    cov_acc = {h: np.zeros((H, W, 3), np.float32) for h in halves}
    nT = 3 if chroma else 1  # one transmittance for all colours unless their kernels differ
    T = {h: np.ones((H, W, nT), np.float32) for h in halves}
    pending: dict[str, list] = {}
    for li in np.argsort(layers.z_mm, kind="stable"):
        c3 = layers.coc_px[li]
        (y0, y1, x0, x1), alpha, color = _splat_layer(sources, layers, li, int(math.ceil(float(np.max(np.abs(c3))) / 2.0)) + 3)
        for hname, (ba, bc) in _blur_layer(alpha, color, c3, halves, eff, chroma).items():
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
    P = sources.pad
    crop = (slice(P, H - P), slice(P, W - P))
    return {hname: acc[hname][crop] / np.maximum(cov_acc[hname][crop], 1e-6) for hname in halves}
