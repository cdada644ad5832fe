"""Half-disc PSF kernels of the base model and their cache (the maths is in :func:`_half_disc_kernel`)."""

from __future__ import annotations

import functools
import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["PSFShape", "half_disc_kernels", "full_disc_kernels", "stack_centred"]


@dataclass
class PSFShape:
    """Per-node shape of the LEFT-view PSF (all tensors broadcast to (K,)).

    Attributes:
        coc_px: (K,) signed CoC diameter of each node, px (sign picks the half: left half for coc > 0).
        scale: multiplies the disc diameter (1 = thin-lens).
        softness_px: standard deviation of the Gaussian that softens the disc, px (0 = hard edge).
        rim2, rim4: radial weight ``1 + rim2 (rho/R)^2 + rim4 (rho/R)^4`` (0 = uniform disc, > 0 brighter
            rim, < 0 brighter centre), clipped at 0; the PSF is renormalised.
        split: weight of the half-aperture split: the left PSF is ``disc * ((1 - split)/2 + split * half)``,
            so the L/R centroid separation is ``split`` times the ideal 4c/(3 pi) (1 = ideal hard split).
        pixel_box: how the PSF becomes pixel weights, from 0 (a 2-px triangle: the sharp image is linearly
            interpolated between pixel centres) to 1 (a 1-px box: each sharp pixel is a uniform square of
            light); see :func:`_half_disc_kernel`.
        sa_px: spherical aberration: a ray through normalized pupil radius rho lands as if the CoC diameter were
            ``scale c - sa_px (rho^2 - 3/5)`` px (> 0 over-corrected: rim-heavy discs behind focus, larger
            centre-heavy ones in front; the 3/5 keeps the best focus, where DP disparity vanishes, at c = 0);
            see :func:`_pushforward_kernel`.
    """

    coc_px: Tensor
    scale: Tensor
    softness_px: Tensor
    rim2: Tensor
    rim4: Tensor
    split: Tensor
    pixel_box: Tensor | float = 0.0
    sa_px: Tensor | float = 0.0
    clip_dx: Tensor | float = 0.0
    """Vignetting: the pupil is cut by a circle of radius 1 (pupil radii) centred ``clip_dx`` pupil radii along x
    (0: no cut; a cat's-eye pupil off axis, where a lens element other than the stop clips the beam)."""
    split_dx: Tensor | float = 0.0
    """Where the photodiodes' split line crosses the pupil, pupil radii along x: the left photodiode takes the
    pupil part :math:`u_x < ` ``split_dx`` (0: the ideal half; off axis the chief ray's angle moves it). The
    kernel keeps its shape only (it sums to 1); the share of light each view gets is applied by the component
    that moves the split (:func:`split_share`)."""
    clip_dy: Tensor | float = 0.0
    """Vignetting along y: the cutting circle's centre is at (``clip_dx``, ``clip_dy``) pupil radii (a cat's-eye
    pupil is cut along the field vector, so off axis in y it is cut from above or below)."""
    f_number: float = 0.0
    """The f-number of the pairs being rendered (0: not known); context for components whose PSF depends on
    the aperture (:attr:`neural_dp.simulators.base.model.Component.shape_needs_optics`), not a kernel input."""
    pixel_pitch_mm: float = 0.0
    """Their output pixel pitch (mm); context like ``f_number``."""


FINE_SUPERSAMPLE_BY_KERNEL_PX: tuple[tuple[int, int], ...] = ((9, 15), (25, 7), (2**31, 5))
"""(largest kernel width n in px, fine samples per px): small kernels, where the disc's edge is a large part
of the PSF, are built on a finer grid; every factor is odd so that a fine sample sits on each pixel centre."""


def _fine_supersample(n: int) -> int:
    """Odd sub-pixel grid factor for an n x n kernel (:data:`FINE_SUPERSAMPLE_BY_KERNEL_PX`)."""
    return next(ss for n_max, ss in FINE_SUPERSAMPLE_BY_KERNEL_PX if n <= n_max)


def _band_matrix(n_in: int, taps: np.ndarray, step: int, offset: int, n_out: int) -> np.ndarray:
    """(n_in, n_out) matrix ``M[j, i] = taps[j - i step + offset]`` (0 outside the taps): ``x @ M`` is the
    correlation of the rows of ``x`` with ``taps`` sampled every ``step`` samples, starting ``offset`` samples
    before the first one (zero outside ``x``). Two such products apply a separable filter as matrix products,
    which are far cheaper than ``conv2d`` on the fine grids here."""
    j = np.arange(n_in).reshape(-1, 1)
    i = np.arange(n_out).reshape(1, -1)
    idx = j - i * step + offset
    inside = (idx >= 0) & (idx < taps.size)
    return np.where(inside, taps[np.clip(idx, 0, taps.size - 1)], np.zeros((), dtype=taps.dtype))


def _gaussian_taps(sigma_fine: float) -> np.ndarray:
    """Normalised Gaussian of standard deviation ``sigma_fine`` samples over ``2 ceil(3 sigma) + 1`` taps, float32."""
    r = int(math.ceil(3 * sigma_fine))
    x = np.arange(2 * r + 1, dtype=np.float32) - np.float32(r)
    g = np.exp(-(x**2) / np.float32(2 * sigma_fine**2))
    return g / g.sum()


@functools.lru_cache(maxsize=256)
def _pixel_projections(n: int, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """(n ss, n) float32 matrices taking a fine grid to pixels along one axis: the 2-px tent sampled at pixel
    centres and the pixel-area sum over ``ss`` samples (divided by ``ss``), see :func:`_to_pixels`."""
    tent = ((1.0 - np.abs(np.arange(-(ss - 1), ss, dtype=np.float32)) / ss) / ss).astype(np.float32)  # (2 ss - 1,)
    tent_band = _band_matrix(n * ss, tent, ss, (ss - 1) // 2, n)
    box_band = (np.arange(n * ss).reshape(-1, 1) // ss == np.arange(n).reshape(1, -1)).astype(np.float32) / np.float32(ss)
    return tent_band, box_band  # shared from the cache: never written (torch.from_numpy needs them writable)


def _to_pixels(w: np.ndarray, n: int, ss: int, beta: float, sigma_fine: float = 0.0) -> Tensor:
    """A fine-grid PSF (n ss, n ss) softened by a Gaussian of ``sigma_fine`` fine samples (zero outside; none
    below 0.3 samples) and taken to (n, n) pixel weights summing to 1: ``(1 - beta)`` tent (sampled at pixel
    centres) ``+ beta`` box (pixel-area mean); see :func:`_half_disc_kernel`.

    The softening and the sampling are separable, so both are one (n ss, n) matrix per axis, ``P = G T``
    (``G`` the Gaussian's band, ``T`` the tent's or the box's): ``P^T w P`` costs (n ss)^2 n, not (n ss)^3."""
    proj = _softened_projection(n, ss, beta > 0, float(sigma_fine))
    right = _matmul(w, proj)  # (n ss, n or 2 n)
    out = _matmul(proj[:, :n].T, right[:, :n])
    if beta > 0:
        out = np.float32(1.0 - beta) * out + np.float32(beta) * _matmul(proj[:, n:].T, right[:, n:])
    out = out / max(float(out.sum()), 1e-12)
    return torch.from_numpy(np.ascontiguousarray(out, dtype=np.float32))


@functools.lru_cache(maxsize=128)
def _softened_projection(n: int, ss: int, with_box: bool, sigma_fine: float) -> np.ndarray:
    """(n ss, n) or, ``with_box``, (n ss, 2 n) float32: the tent's (and the box's) projection to pixels with the
    Gaussian softening of ``sigma_fine`` fine samples folded in (none below 0.3), see :func:`_to_pixels`. Cached:
    every node of a render shares the rim softness, so the kernels of one size share it (never written; left
    writable because ``torch.from_numpy`` needs that)."""
    tent_band, box_band = _pixel_projections(n, ss)
    proj = np.concatenate([tent_band, box_band], axis=1) if with_box else tent_band
    if sigma_fine > 0.3:
        g = _gaussian_taps(sigma_fine)
        r = (g.size - 1) // 2
        proj = _matmul(_band_matrix(n * ss, g, 1, r, n * ss), proj)
    return np.ascontiguousarray(proj)


def _matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` by PyTorch, on the threads it is given (``dp5k diagnose --threads``; numpy's BLAS would take every
    core, which costs more CPU than it saves on matrices this small and oversubscribes parallel runs)."""
    return torch.from_numpy(np.ascontiguousarray(a)).matmul(torch.from_numpy(np.ascontiguousarray(b))).numpy()


_KERNEL_CACHE: "OrderedDict[tuple, Tensor]" = OrderedDict()
_KERNEL_CACHE_SIZE = 4096


def half_disc_kernels(shape: PSFShape, supersample: int = 4) -> Tensor:
    r"""Left-view PSFs of K nodes, each normalised to sum 1 (see :func:`_half_disc_kernel` for the maths).

    Each node's kernel is built at its own size (so the many small kernels near focus are cheap) and kept
    in a small LRU cache keyed by its shape parameters: a fit renders the same nodes for every batch.

    Returns:
        (K, n, n) float tensor, n odd, centred (the largest node's size, others zero-padded); the right
        PSF is ``flip(-1)`` of it.
    """
    coc = shape.coc_px
    K = coc.shape[0]

    def per_node(t: Tensor | float) -> list[float]:
        t = torch.as_tensor(t)
        return (t.reshape(-1).expand(K) if t.numel() == 1 else t.reshape(K)).tolist()

    cols = [per_node(t) for t in (coc, shape.scale, shape.softness_px, shape.rim2, shape.rim4, shape.split, shape.pixel_box, shape.sa_px,
                                  shape.clip_dx, shape.split_dx, shape.clip_dy)]
    kernels = []
    for k in range(K):
        node = tuple(c[k] for c in cols)
        key = (str(coc.device), supersample) + node
        if node[10] < 0.0:  # a pupil cut below the axis: the mirror image, in y, of the cut above it
            kernels.append(_cached_kernel(key[:-1] + (-node[10],), supersample, coc.device).flip(-2))
        else:
            kernels.append(_cached_kernel(key, supersample, coc.device))
    return stack_centred(kernels)


def _cached_kernel(key: tuple, supersample: int, device: torch.device | str) -> Tensor:
    """The kernel of one node, ``key`` = (device, supersample, the node's :class:`PSFShape` fields as floats), from
    :data:`_KERNEL_CACHE` or built.

    A node whose pupil cut sits at ``clip_dy < 0`` is the y-mirror of the node at ``-clip_dy`` (the pupil grid,
    the radial profile and the split are symmetric in pupil y, and pupil y lands along image y):
    :func:`half_disc_kernels` flips that one, the same kernel up to float32 rounding (2e-8 of a 0.05 peak), so
    the nodes of a field-varying PSF below the axis cost no build of their own."""
    ker = _KERNEL_CACHE.get(key)
    if ker is None:
        node = key[2:]
        thin = node[7] == 0.0 and node[8] == 0.0 and node[10] == 0.0  # no sa_px, clip_dx or clip_dy
        build = _half_disc_kernel if thin else _pushforward_kernel
        ker = build(*node, supersample=supersample, device=device)
        _KERNEL_CACHE[key] = ker
        if len(_KERNEL_CACHE) > _KERNEL_CACHE_SIZE:
            _KERNEL_CACHE.popitem(last=False)
    else:
        _KERNEL_CACHE.move_to_end(key)
    return ker


def stack_centred(kernels: Sequence[Tensor], dim: int = 0) -> Tensor:
    """Stack centred odd square kernels (..., n_i, n_i) of different sizes, zero-padded to the largest."""
    n = max(k.shape[-1] for k in kernels)
    return torch.stack([F.pad(k, ((n - k.shape[-1]) // 2,) * 4) for k in kernels], dim=dim)


def _half_disc_kernel(coc_px: float, scale: float, softness_px: float, rim2: float, rim4: float, split: float,
                      pixel_box: float = 0.0, sa_px: float = 0.0, clip_dx: float = 0.0, split_dx: float = 0.0, clip_dy: float = 0.0,
                      supersample: int = 4, device: torch.device | str = "cpu") -> Tensor:
    r"""The left-view PSF of one node (the fields of :class:`PSFShape`, as floats), normalised to sum 1.

    The thin-lens disc without a cut pupil: ``sa_px``, ``clip_dx`` and ``clip_dy`` are taken as 0 (nodes that
    set them are built by :func:`_pushforward_kernel`).

    With radius :math:`R = s |c| / 2` (px), on a fine grid of ``ss`` (odd) samples per pixel:

    .. math::
        D(\rho) = \mathrm{clip}((R' - \rho) ss + 1/2, 0, 1), \quad R' = \max(R, 1/(2 ss))
        P(\rho) = \max(0, 1 + a_2 q + a_4 q^2), \quad q = \min(\rho / R', 1)^2
        S(x) = (1 - k')/2 + k' [x \cdot \mathrm{sign}(c) < s R], \quad k' = k R / R'
        H_l = ((1 - \beta) \mathrm{tent} + \beta\, \mathrm{box})(G_\sigma * (D P S)) / \sum

    ``s`` is ``split_dx`` (the split line's place in the pupil, pupil radii: a ray through pupil x ``u`` lands at
    ``u c / 2`` px, so the left photodiode's part ``u < s`` lands where ``x sign(c) < s R``).
    ``G_sigma`` is a Gaussian of standard deviation ``softness_px`` (the lens' residual blur, px). ``tent``
    samples the fine PSF at pixel centres through a 2-px triangle: the sharp image is reconstructed by
    linear interpolation between pixel centres, so a sub-pixel disc keeps its exact centroid
    (:math:`-2 c / (3 \pi)` px for the left view), i.e. DP disparity does not vanish below 1 px, and
    ``c = 0`` is exactly the identity. ``box`` integrates it over each pixel's area instead (each sharp
    pixel a uniform square of light, as a renderer that draws anti-aliased discs on the pixel grid
    assumes): a half disc inside the centre pixel then stays there (centroid 0 up to ~0.7 px of CoC,
    -0.10 px at 1.3 px against -0.28 exact). ``beta = pixel_box``; ``c = 0`` is the identity for every
    ``beta``. ``supersample`` is a lower bound on ``ss``.

    Returns:
        (n, n) float tensor, n odd, centred; the right PSF is ``flip(-1)`` of it.
    """
    f32 = np.float32
    coc, a2, a4 = f32(coc_px), f32(rim2), f32(rim4)
    beta = min(max(float(pixel_box), 0.0), 1.0)
    R = f32(abs(coc) * f32(scale) / f32(2))  # px
    sigma = max(float(f32(softness_px)), 0.0)
    half = int(math.ceil(float(R) + 3 * sigma)) + 2
    n = 2 * half + 1
    ss = max(_fine_supersample(n), supersample | 1)
    fx, fy, rho = _fine_grid(n, ss)  # (N, N) fine sample centres (px) and their radius
    Reff = max(R, f32(0.5 / ss))
    disc = np.clip((Reff - rho) * f32(ss) + f32(0.5), 0.0, 1.0)
    q = np.minimum(rho / Reff, f32(1.0)) ** 2
    prof_w = np.maximum(f32(1.0) + a2 * q + a4 * q * q, f32(0.0))
    sign = 1.0 if coc_px >= 0 else -1.0
    line = f32(float(split_dx) * float(R))  # px: where the split line lands (x sign(c))
    xs = fx * f32(sign)
    left_half = (xs < line).astype(np.float32) + f32(0.5) * (xs == line).astype(np.float32)
    sk = f32(split) * R / Reff  # a disc below the fine grid's resolution keeps its exact centroid
    w = disc * prof_w * ((f32(1.0) - sk) / f32(2.0) + sk * left_half)
    return _to_pixels(w, n, ss, beta, sigma * ss).to(device)


SA_PUPIL_SAMPLES_MAX = 384
"""Most pupil samples per side of the pushforward grid (:func:`_pushforward_kernel`)."""


@functools.lru_cache(maxsize=64)
def _fine_grid(n: int, ss: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, radius) of the (n ss)^2 fine sample centres of an n x n px kernel, px from its centre, float32."""
    fine = ((np.arange(n * ss, dtype=np.float32) + np.float32(0.5)) / np.float32(ss) - np.float32(n / 2.0)).astype(np.float32)
    fy, fx = np.meshgrid(fine, fine, indexing="ij")
    return _frozen(fx, fy, np.sqrt(fx**2 + fy**2))


@functools.lru_cache(maxsize=64)
def _pupil_grid(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u_x, u_y, rho^2) of the centres of an m x m grid of pupil samples over [-1, 1]^2 that lie in the unit
    disc (flat, float32)."""
    g = ((np.arange(m, dtype=np.float32) + np.float32(0.5)) / np.float32(m) * np.float32(2) - np.float32(1)).astype(np.float32)
    uy, ux = np.meshgrid(g, g, indexing="ij")
    rho2 = ux**2 + uy**2
    inside = rho2 <= 1.0
    return _frozen(ux[inside], uy[inside], rho2[inside])


def _frozen(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """The arrays made read-only (they are shared from a cache)."""
    for a in arrays:
        a.flags.writeable = False
    return arrays


_RHO_ZONES = np.linspace(0.0, 1.0, 101)
"""Pupil radii at which :func:`_pushforward_kernel` finds the largest landing radius."""


def _pushforward_kernel(coc_px: float, scale: float, softness_px: float, rim2: float, rim4: float, split: float,
                        pixel_box: float = 0.0, sa_px: float = 0.0, clip_dx: float = 0.0, split_dx: float = 0.0, clip_dy: float = 0.0,
                        supersample: int = 4, device: torch.device | str = "cpu") -> Tensor:
    r"""The left-view PSF of one node with spherical aberration, as the pushforward of the pupil.

    A ray through the normalized pupil point :math:`u` (:math:`|u| \le 1`, :math:`\rho = |u|`) lands at
    :math:`u\, c_\rho / 2` px from the chief ray, with the zone's CoC diameter
    :math:`c_\rho = s c - a (\rho^2 - 3/5)` (``scale`` s, ``sa_px`` a); with :math:`a = 0` this is the thin-lens
    disc of :func:`_half_disc_kernel`. The pupil is sampled on a regular grid, each sample weighted by the
    radial profile :math:`\max(0, 1 + a_2 \rho^2 + a_4 \rho^4)` and by the split (the left photodiode takes the
    pupil half :math:`u_x < 0`, whose rays land on the left half of the disc behind focus; ``split`` weights
    as in :func:`_half_disc_kernel`), splatted bilinearly on the fine landing grid, softened and sampled to
    pixels like the thin-lens kernel. Zones whose :math:`c_\rho` changes sign land on the other side: that is
    how the PSF inverts its rim between front and back of focus. With ``clip_dx`` / ``clip_dy`` the pupil is also
    cut by a circle of radius 1 centred at (``clip_dx``, ``clip_dy``) (vignetting; pupil y lands along image y,
    downwards, as pupil x lands along image x); each view's PSF still sums to 1 (the
    camera's per-view shading correction restores its brightness). ``split_dx`` moves the split line to
    :math:`u_x = ` ``split_dx``, as in :func:`_half_disc_kernel`.
    """
    f32 = np.float32
    c = float(coc_px) * float(scale)
    a = float(sa_px)
    extent = float(np.abs(_RHO_ZONES * (c - a * (_RHO_ZONES**2 - 0.6))).max()) / 2  # px, largest landing radius
    sigma = max(float(softness_px), 0.0)
    beta = min(max(float(pixel_box), 0.0), 1.0)
    half = int(math.ceil(extent + 3 * sigma)) + 2
    n = 2 * half + 1
    ss = max(_fine_supersample(n), supersample | 1)
    m = int(min(SA_PUPIL_SAMPLES_MAX, max(32, math.ceil(2 * extent * ss * 1.5)))) & ~1  # even: none on u_x = 0
    ux, uy, rho2 = _pupil_grid(m)
    if clip_dx or clip_dy:
        cut = (ux - f32(clip_dx)) ** 2 + (uy - f32(clip_dy)) ** 2 <= 1.0
        ux, uy, rho2 = ux[cut], uy[cut], rho2[cut]
    left = (ux < f32(split_dx)).astype(np.float32)  # the left photodiode's part of the pupil
    w = np.maximum(f32(1.0) + f32(rim2) * rho2 + f32(rim4) * rho2 * rho2, f32(0.0)) * ((f32(1.0) - f32(split)) / f32(2.0) + f32(split) * left)
    zone = f32(c) - f32(a) * (rho2 - f32(0.6))
    N = n * ss
    fx = (ux * zone / f32(2) + f32(n / 2.0)) * f32(ss) - f32(0.5)  # fine-grid coordinates of the landing points
    fy = (uy * zone / f32(2) + f32(n / 2.0)) * f32(ss) - f32(0.5)
    x0, y0 = np.floor(fx), np.floor(fy)
    tx, ty = fx - x0, fy - y0
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    # bilinear splat: the four neighbours of every landing point (all inside the grid: the kernel's half-width
    # exceeds the largest landing radius by at least 2 px)
    idx = np.concatenate([y0 * N + x0, y0 * N + x0 + 1, (y0 + 1) * N + x0, (y0 + 1) * N + x0 + 1])
    wts = np.concatenate([w * (1 - tx) * (1 - ty), w * tx * (1 - ty), w * (1 - tx) * ty, w * tx * ty])
    fine = np.bincount(idx, wts, minlength=N * N).astype(np.float32).reshape(N, N)
    return _to_pixels(fine, n, ss, beta, sigma * ss).to(device)


def split_share(split_dx: Tensor) -> Tensor:
    r"""The left photodiode's share of a uniform pupil's light when the split line sits at pupil x ``split_dx``
    (pupil radii, clipped to [-1, 1]), as a multiple of the ideal half: :math:`2 A(s)` with

    .. math::  A(s) = \frac{1}{2} + \frac{s \sqrt{1 - s^2} + \arcsin s}{\pi}

    the area of the unit disc left of :math:`u_x = s` over :math:`\pi` (1 at ``split_dx`` 0, about
    :math:`1 + 4 s / \pi` near it). The right photodiode's is ``split_share(-split_dx)`` (they add to 2)."""
    s = split_dx.clamp(-1.0, 1.0)
    return 1.0 + 2.0 * (s * torch.sqrt((1.0 - s * s).clamp(min=0.0)) + torch.asin(s)) / math.pi


def full_disc_kernels(nodes: Tensor, supersample: int) -> Tensor:
    """(K, 1, n, n) hard full-disc PSFs of diameter ``|nodes|`` px (a half-disc with ``split = 0``)."""
    one = torch.ones((), device=nodes.device)
    zero = one * 0.0
    return half_disc_kernels(PSFShape(nodes, one, zero, zero, zero, zero), supersample)[:, None]
