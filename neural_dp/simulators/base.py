"""The physical base model: the ideal thin-lens DP model, occlusion-aware, with two fitted parameters.

Each DP view integrates exactly one half of the aperture (a hard split through the disc centre); the
right PSF is the hflip of the left (Eq. 2). For ``coc > 0`` (behind focus) the left view's light lands on
the left half of the disc (docs/conventions.md), mirrored for ``coc < 0``. The only free parameters are
the softness of the disc's rim (``rim_softness_px``) and an overall ``gain``::

    I_l = gain * H_l(|c|, s) * I_s / 2,   I_r = gain * hflip(H_l) * I_s / 2,   sum H_l = 1

Rendering from RGBD is layered and occlusion-aware: the signed CoC range is cut into nodes (soft, linear
assignment of each pixel to its two neighbouring nodes); each node's premultiplied colour and alpha are
blurred with that node's half-disc PSF (FFT), composited front to back (near = most negative CoC first,
since CoC grows monotonically with depth), and normalised by the accumulated coverage (no dark seams at
depth edges or image borders).

Effects the base model lacks (L/R gain imbalance, field dependence, colour dependence, ...) are added as
:class:`Component` objects: each may change the per-channel CoC map, the per-node PSF shape (per colour
channel and field radius) or the rendered views, and carries its own parameters fitted on training data.
``dp5k_diagnose.components`` holds the effect vocabulary's components.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import astuple, dataclass, replace
from typing import ClassVar

import numpy as np
import torch
from scipy.fft import next_fast_len
import torch.nn.functional as F
from torch import Tensor

from dp5k_common.dataset import SHARP_F_NUMBER

from ..batch import DPBatch
from ..metrics import gaussian_window
from .interface import DPSimulator

__all__ = ["PSFShape", "Component", "RenderConfig", "BaseModel", "half_disc_kernels", "field_coords", "fit_parameters"]


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
    """

    coc_px: Tensor
    scale: Tensor
    softness_px: Tensor
    rim2: Tensor
    rim4: Tensor
    split: Tensor
    pixel_box: Tensor | float = 0.0


@dataclass
class RenderConfig:
    """Discretisation of the layered renderer.

    Attributes:
        node_step_px: smallest spacing of CoC nodes (near focus), px (soft assignment between neighbours).
        node_rel_step: spacing of nodes away from focus as a fraction of |CoC| (used where larger than
            ``node_step_px``).
        max_nodes: cap on the number of nodes (the spacings grow to respect it).
        occlude_min_px, occlude_rel: a node occludes a farther one only when their CoCs differ by more than
            ``max(occlude_min_px, occlude_rel * max |CoC|)``; nearer nodes of about the same blur are one
            surface and join the transmittance together (:func:`render_layers`).
        supersample: sub-pixel grid factor used to build kernels.
        chunk: pairs rendered at once (memory bound).
    """

    node_step_px: float = 0.25
    node_rel_step: float = 0.08
    max_nodes: int = 48
    occlude_min_px: float = 2.0
    occlude_rel: float = 0.25
    supersample: int = 4
    chunk: int = 4


class Component(torch.nn.Module):
    """One physical effect added to the base model, with parameters fitted on training data.

    Override any of the hooks. ``params`` holds the fitted parameters by name (floats);
    ``fit_names`` lists those the generic fitter adjusts, ``bounds`` their ranges, ``steps`` the finite
    difference step used for their Jacobian.
    """

    name: ClassVar[str] = "component"
    channel_dependent: ClassVar[bool] = False
    field_dependent: ClassVar[bool] = False
    changes_psf: ClassVar[bool] = False
    post_only: ClassVar[bool] = False
    """True when the component only has a :meth:`post` hook (its fit can reuse one layered render)."""

    def __init__(self) -> None:
        super().__init__()
        self.params: dict[str, float] = {}
        self.fit_names: list[str] = []
        self.bounds: dict[str, tuple[float, float]] = {}
        self.steps: dict[str, float] = {}

    def coc(self, coc_px: Tensor, batch: DPBatch, field: Tensor) -> Tensor:
        """(B, 1 or 3, H, W) signed CoC per colour channel, px (``field`` (B, 2, H, W)). Default: unchanged."""
        return coc_px

    def sharp(self, sharp: Tensor, batch: DPBatch) -> Tensor:
        """(B, 3, H, W) the sharp input as the renderer should see it. Default: unchanged."""
        return sharp

    def shape(self, shape: PSFShape, channel: int, field_r2: float) -> PSFShape:
        """The PSF shape for colour ``channel`` (0..2, or -1 for all) at squared field radius ``field_r2``."""
        return shape

    def post(self, left: Tensor, right: Tensor, batch: DPBatch, field: Tensor) -> tuple[Tensor, Tensor]:
        """Change the rendered views (B, 3, H, W); ``field`` is (B, 2, H, W) in [-1, 1]."""
        return left, right

    def initial_guess(self, model: "BaseModel", batch: DPBatch, field: Tensor) -> None:
        """Set a starting point for the fitter from data (optional)."""

    def supported_names(self, samples: Sequence[object]) -> list[str]:
        """The ``fit_names`` the fit data ``samples`` can constrain (default: all); the rest stay neutral."""
        return list(self.fit_names)

    def describe(self) -> dict[str, float]:
        """Parameters to report (default: ``params``)."""
        return dict(self.params)


def field_coords(batch_size: int, H: int, W: int, device: torch.device | str = "cpu", origin: tuple[int, int] = (0, 0), full_size: tuple[int, int] | None = None) -> Tensor:
    """(B, 2, H, W) field coordinates (x, y) in [-1, 1] of the full image (optical centre = image centre).

    Args:
        origin: (x0, y0) of this crop inside the full image, px.
        full_size: (W, H) of the full image (default: the crop itself).
    """
    Wf, Hf = full_size if full_size is not None else (W, H)
    x0, y0 = origin
    xs = (torch.arange(W, device=device, dtype=torch.float32) + x0 - (Wf - 1) / 2) / ((Wf - 1) / 2)
    ys = (torch.arange(H, device=device, dtype=torch.float32) + y0 - (Hf - 1) / 2) / ((Hf - 1) / 2)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy])[None].expand(batch_size, 2, H, W).contiguous()


def field_r2(field: Tensor) -> Tensor:
    """(B, 1, H, W) squared field radius normalised so that the image corner is 1."""
    return (field[:, :1] ** 2 + field[:, 1:2] ** 2) / 2.0


def _fine_supersample(n: int) -> int:
    """Odd sub-pixel grid factor for an n x n kernel (odd, so that a fine sample sits on every pixel centre)."""
    return 15 if n <= 9 else (7 if n <= 25 else 5)


def _soften(w: Tensor, sigma_fine: float) -> Tensor:
    """(N, N) fine-grid PSF convolved with a Gaussian of ``sigma_fine`` fine samples (zero outside);
    unchanged below 0.3 samples."""
    if sigma_fine <= 0.3:
        return w
    r = int(math.ceil(3 * sigma_fine))
    g = gaussian_window(2 * r + 1, sigma_fine, device=w.device)
    w = F.conv2d(F.pad(w[None, None], (r, r, 0, 0)), g.view(1, 1, 1, -1))
    return F.conv2d(F.pad(w, (0, 0, r, r)), g.view(1, 1, -1, 1))[0, 0]


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

    cols = [per_node(t) for t in (coc, shape.scale, shape.softness_px, shape.rim2, shape.rim4, shape.split, shape.pixel_box)]
    kernels = []
    for k in range(K):
        node = tuple(c[k] for c in cols)
        key = (str(coc.device), supersample) + node
        ker = _KERNEL_CACHE.get(key)
        if ker is None:
            ker = _half_disc_kernel(*node, supersample=supersample, device=coc.device)
            _KERNEL_CACHE[key] = ker
            if len(_KERNEL_CACHE) > _KERNEL_CACHE_SIZE:
                _KERNEL_CACHE.popitem(last=False)
        else:
            _KERNEL_CACHE.move_to_end(key)
        kernels.append(ker)
    return _stack_centred(kernels)


def _stack_centred(kernels: Sequence[Tensor], dim: int = 0) -> Tensor:
    """Stack centred odd square kernels (..., n_i, n_i) of different sizes, zero-padded to the largest."""
    n = max(k.shape[-1] for k in kernels)
    return torch.stack([F.pad(k, ((n - k.shape[-1]) // 2,) * 4) for k in kernels], dim=dim)


def _half_disc_kernel(coc_px: float, scale: float, softness_px: float, rim2: float, rim4: float, split: float,
                      pixel_box: float = 0.0, supersample: int = 4, device: torch.device | str = "cpu") -> Tensor:
    r"""The left-view PSF of one node (the fields of :class:`PSFShape`, as floats), normalised to sum 1.

    With radius :math:`R = s |c| / 2` (px), on a fine grid of ``ss`` (odd) samples per pixel:

    .. math::
        D(\rho) = \mathrm{clip}((R' - \rho) ss + 1/2, 0, 1), \quad R' = \max(R, 1/(2 ss))
        P(\rho) = \max(0, 1 + a_2 q + a_4 q^2), \quad q = \min(\rho / R', 1)^2
        S(x) = (1 - k')/2 + k' [x \cdot \mathrm{sign}(c) < 0], \quad k' = k R / R'
        H_l = ((1 - \beta) \mathrm{tent} + \beta\, \mathrm{box})(G_\sigma * (D P S)) / \sum

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
    coc, scale_t, soft, a2, a4, split_t = (torch.tensor(v, device=device, dtype=torch.float32)
                                            for v in (coc_px, scale, softness_px, rim2, rim4, split))
    beta = min(max(float(pixel_box), 0.0), 1.0)
    R = coc.abs() * scale_t / 2  # px
    sigma = soft.clamp(min=0.0)
    half = int(math.ceil(float(R + 3 * sigma))) + 2
    n = 2 * half + 1
    ss = max(_fine_supersample(n), supersample | 1)
    fine = (torch.arange(n * ss, device=device, dtype=torch.float32) + 0.5) / ss - n / 2.0  # fine sample centres
    fy, fx = torch.meshgrid(fine, fine, indexing="ij")
    rho = torch.sqrt(fx**2 + fy**2)  # (N, N)
    Reff = R.clamp(min=0.5 / ss)
    disc = ((Reff - rho) * ss + 0.5).clamp(0.0, 1.0)
    q = (rho / Reff).clamp(max=1.0) ** 2
    prof_w = (1.0 + a2 * q + a4 * q * q).clamp(min=0.0)
    sign = 1.0 if coc_px >= 0 else -1.0
    left_half = (fx * sign < 0).float() + 0.5 * (fx == 0).float()
    sk = split_t * R / Reff  # a disc below the fine grid's resolution keeps its exact centroid
    w = _soften(disc * prof_w * ((1.0 - sk) / 2.0 + sk * left_half), float(sigma) * ss)
    tent = (1.0 - torch.arange(-(ss - 1), ss, device=device, dtype=torch.float32).abs() / ss) / ss  # (2 ss - 1,)
    p = (ss - 1) // 2
    wp = F.pad(w[None, None], (p, p, p, p))
    out = F.conv2d(F.conv2d(wp, tent.view(1, 1, 1, -1), stride=(1, ss)), tent.view(1, 1, -1, 1), stride=(ss, 1))[0, 0]
    if beta > 0:  # pixel i holds the fine samples i ss .. i ss + ss - 1, centred on its centre like the tent's
        box = w.reshape(n, ss, n, ss).sum(dim=(1, 3)) / (ss * ss)
        out = (1.0 - beta) * out + beta * box
    return out / out.sum().clamp(min=1e-12)


def _nodes(coc: Tensor, valid: Tensor, cfg: RenderConfig) -> Tensor:
    """(K,) CoC nodes on a fixed grid covering the valid CoC range (at least 2 nodes).

    Spacing ``max(step, rel * |c|)`` outward from 0 (``step = node_step_px``, ``rel = node_rel_step``): a
    blend of two neighbouring kernels stands in for the kernel between them, which is accurate when their
    sizes differ little relative to the blur itself; near focus, where a quarter pixel changes the blur's
    frequency response most, the steps are smallest. The grid does not move when the CoC map changes
    slightly (a fitted parameter's finite difference), so interpolation error stays constant and Jacobians
    stay clean; ``step`` and ``rel`` grow in fixed ratios only when the range needs more than ``max_nodes``.
    """
    v = coc[valid.expand_as(coc)] if valid is not None else coc.reshape(-1)
    if v.numel() == 0:
        v = coc.reshape(-1)
    lo, hi = float(v.min()), float(v.max())
    grid: list[float] = []
    for f in (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0, 64.0):
        step, rel = cfg.node_step_px * f, cfg.node_rel_step * f
        grid = _node_side(max(hi, 0.0), step, rel)
        neg = _node_side(max(-lo, 0.0), step, rel)
        grid = [-x for x in reversed(neg[1:])] + grid
        # keep the nodes that bracket [lo, hi]
        i0 = max(0, max((i for i, x in enumerate(grid) if x <= lo), default=0))
        i1 = min(len(grid) - 1, min((i for i, x in enumerate(grid) if x >= hi), default=len(grid) - 1))
        grid = grid[i0 : max(i1, i0 + 1) + 1]
        if len(grid) <= cfg.max_nodes:
            break
    return torch.tensor(grid, device=coc.device, dtype=torch.float32)


def _node_side(extent: float, step: float, rel: float) -> list[float]:
    """Nodes 0, c1, c2, ... with ``c_{k+1} = c_k + max(step, rel c_k)`` until one reaches ``extent``."""
    out = [0.0]
    while out[-1] <= extent:
        out.append(out[-1] + max(step, rel * out[-1]))
    return out


def _embed_kernel_fft(kernels: Tensor, Hp: int, Wp: int) -> Tensor:
    """rfft2 of (..., n, n) kernels placed with their centre at (0, 0) of an (Hp, Wp) grid."""
    n = kernels.shape[-1]
    h = n // 2
    big = kernels.new_zeros(kernels.shape[:-2] + (Hp, Wp))
    big[..., :n, :n] = kernels
    big = torch.roll(big, shifts=(-h, -h), dims=(-2, -1))
    return torch.fft.rfft2(big)


DIRECT_MAX_PX = 9
"""Kernels whose support is at most this many px wide are applied by direct convolution on the node's
bounding box (most nodes near focus); larger ones by FFT over the whole frame."""


def _support(k: Tensor, tol: float = 1e-7) -> int:
    """Half-width (px) of the centred square holding every entry of ``k`` (..., n, n) above ``tol``."""
    n = k.shape[-1]
    h = n // 2
    nz = (k.abs() > tol).reshape(-1, n, n).any(0)
    ys, xs = torch.nonzero(nz, as_tuple=True)
    if ys.numel() == 0:
        return 0
    return int(max((ys - h).abs().max(), (xs - h).abs().max()))


def _fractional_index(coc: Tensor, nodes: Tensor) -> Tensor:
    """Fractional node index of each CoC value: ``k + (c - c_k) / (c_{k+1} - c_k)`` for the bracketing
    nodes (values outside the nodes' range clamp to its ends)."""
    K = nodes.shape[0]
    c = coc.clamp(float(nodes[0]), float(nodes[-1])).contiguous()
    i = (torch.searchsorted(nodes, c.reshape(-1), right=True) - 1).clamp(0, K - 2).reshape(c.shape)
    lo, hi = nodes[i], nodes[i + 1]
    return i.float() + (c - lo) / (hi - lo)


def render_layers(sharp: Tensor, coc: Tensor, valid: Tensor, kernel_fn, cfg: RenderConfig) -> tuple[Tensor, Tensor]:
    r"""Occlusion-aware layered DP rendering (before gain).

    Each pixel's colour and unit alpha are split between its two bracketing CoC nodes (linear weights
    :math:`m_k`); each node's premultiplied layer is blurred with its left/right kernel and composited front
    to back (most negative CoC first), normalised by the accumulated coverage:

    .. math::  O = \frac{\sum_k T_k (H_k * m_k I)}{\sum_k T_k (H_k * m_k)}, \qquad
               T_k = \prod_{G} \mathrm{clip}(1 - \textstyle\sum_{j \in G} H_j * m_j, 0, 1)

    A node is occluded only by nearer nodes whose CoC differs from its own by more than
    ``max(occlude_min_px, occlude_rel * max|C|)`` px; those join the transmittance in groups ``G`` whose
    alphas add, once the first node clearly behind them comes. So a pixel split between two neighbouring
    nodes (:math:`m + (1 - m) = 1`) stays opaque to what lies behind it, and the bins of one continuous
    surface do not occlude each other (no seams).

    Args:
        sharp: (B, 3, H, W) linear sharp image.
        coc: (B, Cc, H, W), Cc in {1, 3}: signed CoC per pixel (per colour channel), px.
        valid: (B, 1, H, W) bool; only used to choose the node range.
        kernel_fn: ``nodes (K,) -> (K, Ck, n, n)`` left-view kernels, Ck in {1, 3}.
        cfg: discretisation.

    Returns:
        left, right: (B, 3, H, W), each ``H * sharp`` (PSFs sum to 1; no factor 1/2 yet).
    """
    B, _, H, W = sharp.shape
    nodes = _nodes(coc, valid, cfg)
    K = nodes.shape[0]
    kl = kernel_fn(nodes)  # (K, Ck, n, n)
    Ck, n = kl.shape[1], kl.shape[-1]
    pad = n // 2 + 1
    Hp, Wp = next_fast_len(H + 2 * pad, real=True), next_fast_len(W + 2 * pad, real=True)
    support = [_support(kl[k]) for k in range(K)]
    big = [k for k in range(K) if 2 * support[k] + 1 > DIRECT_MAX_PX]
    spectra: dict[int, tuple[Tensor, Tensor]] = {}  # node -> rfft2 of its left and right kernels (Ck, Hp, Wf)
    if big:
        fl, fr = _embed_kernel_fft(kl[big], Hp, Wp), _embed_kernel_fft(kl[big].flip(-1), Hp, Wp)
        spectra = {k: (fl[i], fr[i]) for i, k in enumerate(big)}
    per_channel = Ck == 3 or coc.shape[1] == 3
    nc = 3 if per_channel else 1
    t = _fractional_index(coc, nodes)  # (B, Cc, H, W)
    node_c = [float(c) for c in nodes]

    def occludes(c_near: float, c_far: float) -> bool:
        return c_far - c_near > max(cfg.occlude_min_px, cfg.occlude_rel * max(abs(c_near), abs(c_far)))

    outs = []
    for b0 in range(0, B, cfg.chunk):
        s = sharp[b0 : b0 + cfg.chunk]
        tt = t[b0 : b0 + cfg.chunk]
        nb = s.shape[0]
        acc = {v: torch.zeros_like(s) for v in ("l", "r")}
        cov = {v: torch.zeros(nb, nc, H, W, device=s.device) for v in ("l", "r")}
        trans = {v: torch.ones(nb, nc, H, W, device=s.device) for v in ("l", "r")}
        pending: list[tuple[float, dict[str, Tensor]]] = []
        for k in range(K):
            m = (1.0 - (tt - k).abs()).clamp(min=0.0)  # (nb, Cc, H, W) soft membership
            hit = (m > 0).flatten(0, 1).any(0)
            if not bool(hit.any()):
                continue
            group = [p for p in pending if occludes(p[0], node_c[k])]
            if group:
                for v in ("l", "r"):
                    trans[v] = trans[v] * (1.0 - sum(p[1][v] for p in group)).clamp(0.0, 1.0)
                pending = [p for p in pending if not occludes(p[0], node_c[k])]
            m = m.expand(nb, 3, H, W) if per_channel else m
            sig = torch.cat([s * m, m], dim=1)  # (nb, 3 + nc, H, W)
            blurred = _blur_node(sig, kl[k], support[k], hit, spectra.get(k), pad, Hp, Wp)
            alphas = {}
            for v in ("l", "r"):
                col, alpha = blurred[v][:, :3], blurred[v][:, 3 : 3 + nc].clamp(0.0, 1.0)
                acc[v] = acc[v] + trans[v] * col
                cov[v] = cov[v] + trans[v] * alpha
                alphas[v] = alpha
            pending.append((node_c[k], alphas))
        outs.append(tuple(acc[v] / cov[v].clamp(min=1e-6) for v in ("l", "r")))
    return torch.cat([o[0] for o in outs]), torch.cat([o[1] for o in outs])


def _blur_node(sig: Tensor, kernel: Tensor, support: int, hit: Tensor, spectra: tuple[Tensor, Tensor] | None,
               pad: int, Hp: int, Wp: int) -> dict[str, Tensor]:
    """Blur one node's layer ``sig`` (B, C, H, W: colour then alpha, C = 4 or 6) with its left kernel
    ``kernel`` (Ck, n, n) and its hflip; per-channel kernels (Ck = 3) come with C = 6.

    Small kernels (``spectra`` None) are applied by direct convolution inside the bounding box of ``hit``
    (H, W bool, where the node has members) grown by the kernel's ``support``; large ones by FFT
    (``spectra``: the left and right kernels' rfft2 on the (Hp, Wp) grid).

    Returns:
        {"l": (B, C, H, W), "r": (B, C, H, W)}.
    """
    B, C, H, W = sig.shape
    if spectra is None:
        rows = torch.nonzero(hit.any(1)).flatten()
        cols = torch.nonzero(hit.any(0)).flatten()
        y0, y1 = max(int(rows[0]) - support, 0), min(int(rows[-1]) + support + 1, H)
        x0, x1 = max(int(cols[0]) - support, 0), min(int(cols[-1]) + support + 1, W)
        h = kernel.shape[-1] // 2
        k = kernel[..., h - support : h + support + 1, h - support : h + support + 1]  # (Ck, n', n')
        ys0, xs0 = max(y0 - support, 0), max(x0 - support, 0)
        ys1, xs1 = min(y1 + support, H), min(x1 + support, W)
        src = F.pad(sig[..., ys0:ys1, xs0:xs1], (support - (x0 - xs0), support - (xs1 - x1), support - (y0 - ys0), support - (ys1 - y1)))
        out = {}
        for v, kv in (("l", k), ("r", k.flip(-1))):
            w = kv.expand(C, -1, -1) if kv.shape[0] == 1 else torch.cat([kv, kv], 0)  # colour, then alpha
            w = w.flip(-1, -2)[:, None]  # conv2d correlates: flip for a true convolution (light spreading)
            res = sig.new_zeros(B, C, H, W)
            res[..., y0:y1, x0:x1] = F.conv2d(src, w, groups=C)
            out[v] = res
        return out
    sigp = F.pad(sig, (pad, Wp - W - pad, pad, Hp - H - pad))
    fs = torch.fft.rfft2(sigp)
    out = {}
    for v, fk in zip(("l", "r"), spectra):
        if C == 6:
            kk = fk if fk.shape[0] == 3 else fk.expand(3, *fk.shape[1:])
            prod = fs * torch.cat([kk, kk], dim=0)[None]
        else:
            prod = fs * fk[None]
        out[v] = torch.fft.irfft2(prod, s=(Hp, Wp))[..., pad : pad + H, pad : pad + W]
    return out


_RADIANCE_CACHE: "OrderedDict[tuple, tuple[Tensor, Tensor, Tensor, Tensor | None]]" = OrderedDict()
_RADIANCE_CACHE_BYTES = 512 * 2**20
"""The cache keeps each entry's sharp, CoC and radiance tensors alive; it is bounded by their total size."""


def sharp_blur_coc_px(batch: DPBatch) -> Tensor:
    r"""(B, 1, H, W) signed CoC diameter of the sharp frame's own blur, output px.

    Eq. 6 is proportional to :math:`1/N` at fixed focus, so the sharp frame, taken at :math:`N_s` with the
    same focus, blurs each point by :math:`C_s = C \, N / N_s` (``C`` = ``batch.coc_px``, the DP capture's
    CoC). :math:`N_s` is ``batch.sharp_f_number`` (:data:`SHARP_F_NUMBER` when absent); :math:`N_s = 0`
    marks an all-in-focus sharp image (:math:`C_s = 0`).
    """
    B = batch.sharp.shape[0]
    ns = batch.sharp_f_number if batch.sharp_f_number is not None else torch.full((B,), SHARP_F_NUMBER)
    ns = ns.to(batch.coc_px.device, torch.float32)
    ratio = torch.where(ns > 0, batch.f_number.float() / ns.clamp(min=1e-6), torch.zeros_like(ns))
    return batch.coc_px.float() * ratio.view(B, 1, 1, 1)


def _full_disc_kernels(nodes: Tensor, supersample: int) -> Tensor:
    """(K, 1, n, n) hard full-disc PSFs of diameter ``|nodes|`` px (a half-disc with ``split = 0``)."""
    one = torch.ones((), device=nodes.device)
    zero = one * 0.0
    return half_disc_kernels(PSFShape(nodes, one, zero, zero, zero, zero), supersample)[:, None]


def sharp_radiance(batch: DPBatch, iters: int = 2, config: RenderConfig | None = None) -> Tensor:
    r"""(B, 3, H, W) the all-in-focus radiance behind the sharp frame, linear, the sharp frame's scale.

    The sharp frame :math:`s` is a capture at :math:`N_s` (f/22), blurred per pixel by a disc of diameter
    :math:`|C_s|` (:func:`sharp_blur_coc_px`): :math:`s = B x`, with :math:`B` the same occlusion-aware
    layered blur the model renders with (full disc). Van Cittert iterations undo it:
    :math:`x_0 = s,\ x_{k+1} = x_k + (s - B x_k)`. At f/2.8 the sharp frame's disc is 13 % of the DP
    capture's; treating the frame as a pinhole image leaves a rim-softening error 3-25 x the renderer's own
    on a slanted plane (docs/diagnose.md, base model); one iteration removes about 90 % of it, two reach the
    renderer's floor. Discs under 2.4 px keep :math:`|1 - \hat B| < 1` below Nyquist, so the iteration
    converges where the DP blur lets detail through. ``iters = 0`` returns ``s``. Results are cached per
    (sharp, coc, sharp f-numbers) tensors, iterations and discretisation: fits render the same batch many
    times (:data:`_RADIANCE_CACHE_BYTES` bounds the cache).
    """
    if iters <= 0 or batch.sharp_f_number is not None and bool((batch.sharp_f_number <= 0).all()):
        return batch.sharp.float()
    cfg = config or RenderConfig()
    key = (id(batch.sharp), id(batch.coc_px), id(batch.sharp_f_number), int(iters), astuple(cfg))
    hit = _RADIANCE_CACHE.get(key)
    if hit is not None and hit[0] is batch.sharp and hit[1] is batch.coc_px and hit[3] is batch.sharp_f_number:
        _RADIANCE_CACHE.move_to_end(key)
        return hit[2]
    s = batch.sharp.float()
    coc_s = sharp_blur_coc_px(batch)

    def blur(x: Tensor) -> Tensor:
        return render_layers(x, coc_s, batch.valid, lambda nodes: _full_disc_kernels(nodes, cfg.supersample), cfg)[0]

    x = s
    for _ in range(iters):
        x = x + (s - blur(x))
    _RADIANCE_CACHE[key] = (batch.sharp, batch.coc_px, x, batch.sharp_f_number)
    def nbytes(entry: tuple) -> int:
        return sum(t.numel() * t.element_size() for t in entry if isinstance(t, Tensor))

    total = sum(nbytes(e) for e in _RADIANCE_CACHE.values())
    while len(_RADIANCE_CACHE) > 1 and total > _RADIANCE_CACHE_BYTES:
        total -= nbytes(_RADIANCE_CACHE.popitem(last=False)[1])
    return x


class BaseModel(DPSimulator):
    """The ideal occlusion-aware thin-lens DP model (half-aperture split) plus optional effect components.

    Args:
        rim_softness_px: standard deviation of the Gaussian that softens the disc (residual lens blur), px.
        gain: overall intensity gain (views are ``gain * H * sharp / 2``).
        components: effect components (see :class:`Component`), applied in order.
        config: renderer discretisation.
        sharp_deblur_iters: Van Cittert iterations that undo the sharp frame's own f/22 blur before
            rendering (:func:`sharp_radiance`; 0 treats the sharp frame as a pinhole image).
        pixel_box: how PSFs become pixel weights, 0 (2-px triangle: linear interpolation of the sharp image)
            to 1 (1-px box: pixel-area integration), :class:`PSFShape`; a renderer-discretisation parameter
            that :func:`dp5k_diagnose.detect.fit_base` fits with the rim softness and the gain.
    """

    name: ClassVar[str] = "base"

    def __init__(self, rim_softness_px: float = 0.5, gain: float = 1.0, components: Sequence[Component] = (), config: RenderConfig | None = None,
                 sharp_deblur_iters: int = 2, pixel_box: float = 0.0) -> None:
        super().__init__()
        self.sharp_deblur_iters = int(sharp_deblur_iters)
        self.params: dict[str, float] = {"rim_softness_px": float(rim_softness_px), "gain": float(gain), "pixel_box": float(pixel_box)}
        self.bounds: dict[str, tuple[float, float]] = {"rim_softness_px": (0.0, 6.0), "gain": (0.05, 20.0), "pixel_box": (0.0, 1.0)}
        self.steps: dict[str, float] = {"rim_softness_px": 0.15, "gain": 0.01, "pixel_box": 0.25}
        self.components = torch.nn.ModuleList(list(components))
        self.config = config or RenderConfig()

    # -- composition -----------------------------------------------------------------------------
    def with_component(self, comp: Component) -> "BaseModel":
        """A new model with the same base parameters and components plus ``comp``."""
        return self.replaced(list(self.components) + [comp])

    def replaced(self, components: Sequence[Component] | None = None, **params: float) -> "BaseModel":
        """A new model with these ``components`` (default: the same) and base ``params`` changed, the rest kept."""
        p = {**self.params, **params}
        return BaseModel(p["rim_softness_px"], p["gain"], list(self.components) if components is None else list(components),
                         self.config, self.sharp_deblur_iters, p["pixel_box"])

    def describe(self) -> dict[str, object]:
        return {"base": dict(self.params), "sharp_deblur_iters": self.sharp_deblur_iters,
                "components": {c.name: c.describe() for c in self.components}}

    # -- rendering -------------------------------------------------------------------------------
    def _shape(self, nodes: Tensor, channel: int, r2: float) -> PSFShape:
        one = torch.ones((), device=nodes.device)
        shape = PSFShape(
            coc_px=nodes,
            scale=one,
            softness_px=one * self.params["rim_softness_px"],
            rim2=one * 0.0,
            rim4=one * 0.0,
            split=one,
            pixel_box=one * self.params["pixel_box"],
        )
        for c in self.components:
            shape = c.shape(shape, channel, r2)
        return shape

    def _kernel_fn(self, r2: float):
        chan = any(c.channel_dependent and c.changes_psf for c in self.components)
        ss = self.config.supersample

        def fn(nodes: Tensor) -> Tensor:
            if not chan:
                return half_disc_kernels(self._shape(nodes, -1, r2), ss)[:, None]
            return _stack_centred([half_disc_kernels(self._shape(nodes, ch, r2), ss) for ch in range(3)], dim=1)

        return fn

    def render_layers_only(self, batch: DPBatch, field: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The layered render before gain and post hooks: (left, right), each ``H * sharp``."""
        B, _, H, W = batch.sharp.shape
        if field is None:
            field = field_coords(B, H, W, batch.sharp.device)
        coc = batch.coc_px.float()
        sharp = sharp_radiance(batch, self.sharp_deblur_iters, self.config)
        for c in self.components:
            coc = c.coc(coc, batch, field)
            sharp = c.sharp(sharp, batch)
        valid = batch.valid
        if any(c.field_dependent and c.changes_psf for c in self.components):
            nodes_r2 = (0.0, 0.5, 1.0)
            renders = [render_layers(sharp, coc, valid, self._kernel_fn(r2), self.config) for r2 in nodes_r2]
            r2 = field_r2(field).clamp(0.0, 1.0)
            w0 = (1 - 2 * r2).clamp(min=0)
            w2 = (2 * r2 - 1).clamp(min=0)
            w1 = 1 - w0 - w2
            left = w0 * renders[0][0] + w1 * renders[1][0] + w2 * renders[2][0]
            right = w0 * renders[0][1] + w1 * renders[1][1] + w2 * renders[2][1]
        else:
            left, right = render_layers(sharp, coc, valid, self._kernel_fn(0.0), self.config)
        return left, right

    def render(self, batch: DPBatch, field: Tensor | None = None, layers: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
        """(left, right), each (B, 3, H, W), linear, on the batch's scale.

        Args:
            field: (B, 2, H, W) field coordinates in [-1, 1] (default: the batch is the whole image).
            layers: a cached :meth:`render_layers_only` result to reuse (only gain and post hooks run).
        """
        B, _, H, W = batch.sharp.shape
        if field is None:
            field = field_coords(B, H, W, batch.sharp.device)
        left, right = layers if layers is not None else self.render_layers_only(batch, field)
        g = self.params["gain"] / 2.0
        left, right = left * g, right * g
        for c in self.components:
            left, right = c.post(left, right, batch, field)
        return left, right

    def forward(self, batch: DPBatch, field: Tensor | None = None) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        with torch.no_grad():
            return self.render(batch, field)

    # -- fitting ---------------------------------------------------------------------------------
    def fit(self, batches: list[DPBatch], fields: list[Tensor] | None = None) -> dict[str, float]:  # type: ignore[override]
        """Fit ``rim_softness_px`` and ``gain`` on training batches (measured views required)."""
        fit_parameters(self, [(self, "rim_softness_px"), (self, "gain")], batches, fields)
        return {k: self.params[k] for k in ("rim_softness_px", "gain")}


def _masked_residual(model: BaseModel, batch: DPBatch, field: Tensor | None, layers: tuple[Tensor, Tensor] | None = None,
                     mask: Tensor | None = None) -> Tensor:
    left, right = model.render(batch, field, layers)
    m = (batch.valid if mask is None else mask).float()
    r = torch.cat([(left - batch.left) * m, (right - batch.right) * m], dim=1)
    return r.reshape(-1)


@torch.no_grad()
def fit_parameters(
    model: BaseModel,
    targets: Sequence[tuple[object, str]],
    batches: list[DPBatch],
    fields: list[Tensor] | None = None,
    iters: int = 4,
    masks: list[Tensor] | None = None,
) -> float:
    """Levenberg-Marquardt fit of named scalar parameters on the masked L/R squared error.

    Args:
        model: the model to fit (parameters are changed in place).
        targets: ``(owner, name)`` pairs; ``owner`` is the model or one of its components, each holding
            ``params``, ``bounds`` and ``steps`` dicts.
        batches: measured batches (left/right set).
        fields: optional per-batch field maps (for crops).
        iters: LM iterations (each costs 1 + len(targets) renders per batch; the gain costs none).
        masks: optional per-batch (B, 1, H, W) masks of the pixels that count (default: ``batch.valid``).

    Returns:
        The final mean squared error.
    """
    fields = fields or [None] * len(batches)
    masks = masks or [b.valid for b in batches]
    post_only = all(o is model and n == "gain" or getattr(o, "post_only", False) for o, n in targets)
    cache = [model.render_layers_only(b, f) for b, f in zip(batches, fields)] if post_only else [None] * len(batches)

    def get() -> np.ndarray:
        return np.array([o.params[n] for o, n in targets], dtype=np.float64)  # type: ignore[attr-defined]

    def put(x: np.ndarray) -> None:
        for (o, n), v in zip(targets, x):
            lo, hi = o.bounds.get(n, (-np.inf, np.inf))  # type: ignore[attr-defined]
            o.params[n] = float(np.clip(v, lo, hi))  # type: ignore[attr-defined]

    def residual() -> Tensor:
        with torch.no_grad():
            return torch.cat([_masked_residual(model, b, f, c, m) for b, f, c, m in zip(batches, fields, cache, masks)]).double()

    x = get()
    r = residual()
    cost = float((r**2).sum())
    lam = 1e-3
    for _ in range(iters):
        cols = []
        for i, (o, n) in enumerate(targets):
            if o is model and n == "gain":
                # views are linear in the gain: d r / d g = (r + measured) / g
                meas = torch.cat([torch.cat([b.left * m, b.right * m], 1).reshape(-1) for b, m in zip(batches, masks)]).double()
                cols.append((r + meas) / max(model.params["gain"], 1e-6))
                continue
            h = o.steps.get(n, 1e-2)  # type: ignore[attr-defined]
            xp = x.copy()
            lo, hi = o.bounds.get(n, (-np.inf, np.inf))  # type: ignore[attr-defined]
            if xp[i] + h > hi:
                h = -h
            xp[i] += h
            put(xp)
            cols.append((residual() - r) / h)
            put(x)
        J = torch.stack(cols, 1)
        JtJ = (J.T @ J).numpy()
        Jtr = (J.T @ r).numpy()
        improved = False
        for _try in range(4):
            A = JtJ + lam * np.diag(np.diag(JtJ) + 1e-12)
            try:
                dx = -np.linalg.solve(A, Jtr)
            except np.linalg.LinAlgError:
                dx = -np.linalg.lstsq(A, Jtr, rcond=None)[0]
            put(x + dx)
            r_new = residual()
            c_new = float((r_new**2).sum())
            if c_new < cost:
                x, r, cost = get(), r_new, c_new
                lam = max(lam / 5, 1e-6)
                improved = True
                break
            put(x)
            lam *= 10
        if not improved:
            break
    put(x)
    return cost / max(r.numel(), 1)
