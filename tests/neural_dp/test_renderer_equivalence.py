"""Equivalence of the optimised renderers with the implementations they replaced (issue 22, target 2).

The ``_reference_*`` functions below are verbatim copies of the renderers as they were before they were
optimised for paper-size images (peer_layers.render_layered with kernels.convolve_same,
raytrace.render_raytrace, base.render.render_layers with its helpers), renamed. They are kept here, and only
here, so that each optimised renderer is compared with today's output on small scenes to 1e-4: the test fails
if an optimisation changes what a simulator renders.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.fft import next_fast_len
from torch import Tensor

from dp5k_common.errors import BadInputError
from neural_dp.batch import DPBatch
from neural_dp.simulators.base import BaseModel
from neural_dp.metrics import gaussian_window
from neural_dp.simulators.base.components import ChromaticDefocus, PSFProfile
from neural_dp.simulators.base.psf import _half_disc_kernel
from neural_dp.simulators.base.render import NODE_SPACING_LADDER, RenderConfig, render_layers
from neural_dp.simulators.butterworth import ButterworthSimulator, butterworth_psf
from neural_dp.simulators.disk import TranslatingDiskSimulator, translating_disk_psf
from neural_dp import kernels
from neural_dp.simulators import peer_layers
from neural_dp.simulators.peer_layers import PsfFn, render_layered
from neural_dp.simulators.raytrace import RayTracingSimulator, aperture_points, render_raytrace

_REFERENCE_DIRECT_MAX_PX = 9


# ---- reference copies (pre-optimisation) --------------------------------------------------------------

def _reference_convolve_same(x: Tensor, psf: Tensor, *, fft_above: int = 21) -> Tensor:
    """True 2-D convolution of every channel with one PSF, zero padding, output the input's size.

    .. math::
        out(y, x) = \\sum_{u,v} psf(v, u)\\, x(y - v, x - u)

    with ``(u, v)`` offsets from the PSF centre: a PSF mass at ``u < 0`` moves content left.

    Args:
        x: (B, C, H, W).
        psf: (k, k) with k odd, on x's device and dtype.
        fft_above: kernels larger than this many taps per side use FFT instead of ``conv2d``.

    Returns:
        (B, C, H, W).
    """
    k = psf.shape[-1]
    if psf.ndim != 2 or psf.shape[0] != k or k % 2 == 0:
        raise BadInputError(f"psf must be square with odd size, got {tuple(psf.shape)}", where="convolve_same")
    B, C, H, W = x.shape
    r = k // 2
    if k <= fft_above:
        weight = psf.flip(0, 1).to(x.dtype)[None, None].expand(C, 1, k, k)
        return F.conv2d(F.pad(x, (r, r, r, r)), weight, groups=C)
    Hp, Wp = H + 2 * r, W + 2 * r
    X = torch.fft.rfft2(x, s=(Hp, Wp))
    K = torch.fft.rfft2(psf.to(x.dtype), s=(Hp, Wp))
    full = torch.fft.irfft2(X * K, s=(Hp, Wp))
    return full[..., r : r + H, r : r + W]


def _reference_render_layered(sharp: Tensor, coc_px: Tensor, valid: Tensor, left_psf: PsfFn, step_px: float = 1.0) -> tuple[Tensor, Tensor]:
    """Render both DP views by depth layers with coverage normalisation (module docstring).

    Args:
        sharp: (B, C, H, W) linear image.
        coc_px: (B, 1, H, W) signed CoC diameter in px.
        valid: (B, 1, H, W) bool.
        left_psf: layer PSF generator (the right PSF is its horizontal flip).
        step_px: layer spacing in CoC diameter px (1 px: layers at every integer CoC, as Abuolaim et al.
            round the CoC to integers).

    Returns:
        (left, right), each (B, C, H, W).
    """
    levels = torch.round(torch.where(valid, coc_px, torch.zeros_like(coc_px)) / step_px).to(torch.int64)
    C = sharp.shape[1]
    num_l = torch.zeros_like(sharp)
    num_r = torch.zeros_like(sharp)
    cover = torch.zeros_like(sharp[:, :1])
    for level in torch.unique(levels).tolist():
        mask = (levels == level).to(sharp.dtype)
        stack = torch.cat([sharp * mask, mask], dim=1)
        psf_l = torch.as_tensor(np.ascontiguousarray(left_psf(level * step_px)), dtype=sharp.dtype, device=sharp.device)
        psf_r = psf_l.flip(1)
        blur_l = _reference_convolve_same(stack, psf_l)
        blur_r = _reference_convolve_same(stack, psf_r)
        num_l += blur_l[:, :C]
        num_r += blur_r[:, :C]
        cover += blur_l[:, C:] + blur_r[:, C:]
    cover = cover.clamp_min(1e-8)
    return num_l / cover, num_r / cover


def _reference_render_raytrace(sharp: Tensor, coc_px: Tensor, valid: Tensor, max_points_side: int = 64) -> tuple[Tensor, Tensor]:
    """Render both DP views by thin-lens ray splatting (module docstring).

    Args:
        sharp: (B, C, H, W) linear image.
        coc_px: (B, 1, H, W) signed CoC diameter in px (invalid pixels are treated as in focus).
        valid: (B, 1, H, W) bool.
        max_points_side: cap on the aperture grid's side (memory/time bound for huge CoCs).

    Returns:
        (left, right), each (B, C, H, W).
    """
    B, C, H, W = sharp.shape
    dev, dt = sharp.device, sharp.dtype
    c = torch.where(valid, coc_px, torch.zeros_like(coc_px)).reshape(-1)
    # Each pixel gets an n x n aperture grid with n >= |C| (even), so its rays land <= 1 px apart.
    n_pix = torch.clamp(torch.ceil(c.abs()), 2, max_points_side).to(torch.int64)
    n_pix = n_pix + n_pix % 2
    yy, xx = torch.meshgrid(torch.arange(H, dtype=dt, device=dev), torch.arange(W, dtype=dt, device=dev), indexing="ij")
    xx = xx.reshape(1, H * W).expand(B, H * W).reshape(-1)
    yy = yy.reshape(1, H * W).expand(B, H * W).reshape(-1)
    base = (torch.arange(B, device=dev) * (H * W)).view(B, 1).expand(B, H * W).reshape(-1)
    src_all = torch.cat([sharp, torch.ones_like(sharp[:, :1])], dim=1).permute(0, 2, 3, 1).reshape(B * H * W, C + 1)
    flat_l = torch.zeros(B * H * W, C + 1, dtype=dt, device=dev)
    flat_r = torch.zeros_like(flat_l)
    for n in torch.unique(n_pix).tolist():
        sel = (n_pix == n).nonzero().squeeze(1)
        pts = aperture_points(int(n), dtype=dt, device=dev)
        src = src_all[sel] / pts.shape[0]
        half = (c[sel] / 2)[None]
        px, py, pbase = xx[sel][None], yy[sel][None], base[sel][None]
        npx = sel.numel()
        chunk = max(1, (1 << 22) // (4 * npx))  # bounded memory: <= ~4M splats per index_add
        for target, side in ((flat_l, pts[pts[:, 0] < 0]), (flat_r, pts[pts[:, 0] > 0])):
            for k in range(0, side.shape[0], chunk):
                x = px + half * side[k : k + chunk, 0:1]  # (Pc, npx)
                y = py + half * side[k : k + chunk, 1:2]
                x0, y0 = torch.floor(x), torch.floor(y)
                fx, fy = x - x0, y - y0
                idx_parts, w_parts = [], []
                for dy, dx, w in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
                    xi, yi = x0 + dx, y0 + dy
                    inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
                    idx_parts.append((pbase + (yi.clamp(0, H - 1) * W + xi.clamp(0, W - 1)).to(torch.int64)).reshape(-1))
                    w_parts.append((w * inside).reshape(-1))
                idx = torch.cat(idx_parts)
                weight = torch.cat(w_parts)
                target.index_add_(0, idx, src.repeat(idx.numel() // npx, 1) * weight[:, None])
    left = flat_l.reshape(B, H, W, C + 1).permute(0, 3, 1, 2)
    right = flat_r.reshape(B, H, W, C + 1).permute(0, 3, 1, 2)
    cover = (left[:, C:] + right[:, C:]).clamp_min(1e-8)
    return left[:, :C] / cover, right[:, :C] / cover


def _reference_render_layers(sharp: Tensor, coc: Tensor, valid: Tensor, kernel_fn, cfg: RenderConfig) -> tuple[Tensor, Tensor]:
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
    nodes = _reference_nodes(coc, valid, cfg)
    K = nodes.shape[0]
    kl = kernel_fn(nodes)  # (K, Ck, n, n)
    Ck, n = kl.shape[1], kl.shape[-1]
    pad = n // 2 + 1
    Hp, Wp = next_fast_len(H + 2 * pad, real=True), next_fast_len(W + 2 * pad, real=True)
    support = [_reference_support(kl[k]) for k in range(K)]
    big = [k for k in range(K) if 2 * support[k] + 1 > _REFERENCE_DIRECT_MAX_PX]
    spectra: dict[int, tuple[Tensor, Tensor]] = {}  # node -> rfft2 of its left and right kernels (Ck, Hp, Wf)
    if big:
        fl, fr = _reference_embed_kernel_fft(kl[big], Hp, Wp), _reference_embed_kernel_fft(kl[big].flip(-1), Hp, Wp)
        spectra = {k: (fl[i], fr[i]) for i, k in enumerate(big)}
    per_channel = Ck == 3 or coc.shape[1] == 3
    nc = 3 if per_channel else 1
    t = _reference_fractional_index(coc, nodes)  # (B, Cc, H, W)
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
            blurred = _reference_blur_node(sig, kl[k], support[k], hit, spectra.get(k), pad, Hp, Wp)
            alphas = {}
            for v in ("l", "r"):
                col, alpha = blurred[v][:, :3], blurred[v][:, 3 : 3 + nc].clamp(0.0, 1.0)
                acc[v] = acc[v] + trans[v] * col
                cov[v] = cov[v] + trans[v] * alpha
                alphas[v] = alpha
            pending.append((node_c[k], alphas))
        outs.append(tuple(acc[v] / cov[v].clamp(min=1e-6) for v in ("l", "r")))
    return torch.cat([o[0] for o in outs]), torch.cat([o[1] for o in outs])


def _reference_blur_node(sig: Tensor, kernel: Tensor, support: int, hit: Tensor, spectra: tuple[Tensor, Tensor] | None,
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


def _reference_nodes(coc: Tensor, valid: Tensor, cfg: RenderConfig) -> Tensor:
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
    for f in NODE_SPACING_LADDER:
        step, rel = cfg.node_step_px * f, cfg.node_rel_step * f
        grid = _reference_node_side(max(hi, 0.0), step, rel)
        neg = _reference_node_side(max(-lo, 0.0), step, rel)
        grid = [-x for x in reversed(neg[1:])] + grid
        # keep the nodes that bracket [lo, hi]
        i0 = max(0, max((i for i, x in enumerate(grid) if x <= lo), default=0))
        i1 = min(len(grid) - 1, min((i for i, x in enumerate(grid) if x >= hi), default=len(grid) - 1))
        grid = grid[i0 : max(i1, i0 + 1) + 1]
        if len(grid) <= cfg.max_nodes:
            break
    return torch.tensor(grid, device=coc.device, dtype=torch.float32)


def _reference_node_side(extent: float, step: float, rel: float) -> list[float]:
    """Nodes 0, c1, c2, ... with ``c_{k+1} = c_k + max(step, rel c_k)`` until one reaches ``extent``."""
    out = [0.0]
    while out[-1] <= extent:
        out.append(out[-1] + max(step, rel * out[-1]))
    return out


def _reference_embed_kernel_fft(kernels: Tensor, Hp: int, Wp: int) -> Tensor:
    """rfft2 of (..., n, n) kernels placed with their centre at (0, 0) of an (Hp, Wp) grid."""
    n = kernels.shape[-1]
    h = n // 2
    big = kernels.new_zeros(kernels.shape[:-2] + (Hp, Wp))
    big[..., :n, :n] = kernels
    big = torch.roll(big, shifts=(-h, -h), dims=(-2, -1))
    return torch.fft.rfft2(big)


def _reference_support(k: Tensor, tol: float = 1e-7) -> int:
    """Half-width (px) of the centred square holding every entry of ``k`` (..., n, n) above ``tol``."""
    n = k.shape[-1]
    h = n // 2
    nz = (k.abs() > tol).reshape(-1, n, n).any(0)
    ys, xs = torch.nonzero(nz, as_tuple=True)
    if ys.numel() == 0:
        return 0
    return int(max((ys - h).abs().max(), (xs - h).abs().max()))


def _reference_fractional_index(coc: Tensor, nodes: Tensor) -> Tensor:
    """Fractional node index of each CoC value: ``k + (c - c_k) / (c_{k+1} - c_k)`` for the bracketing
    nodes (values outside the nodes' range clamp to its ends)."""
    K = nodes.shape[0]
    c = coc.clamp(float(nodes[0]), float(nodes[-1])).contiguous()
    i = (torch.searchsorted(nodes, c.reshape(-1), right=True) - 1).clamp(0, K - 2).reshape(c.shape)
    lo, hi = nodes[i], nodes[i + 1]
    return i.float() + (c - lo) / (hi - lo)


def _reference_fine_supersample(n: int) -> int:
    return next(ss for n_max, ss in ((9, 15), (25, 7), (2**31, 5)) if n <= n_max)


def _reference_soften(w: Tensor, sigma_fine: float) -> Tensor:
    """(N, N) fine-grid PSF convolved with a Gaussian of ``sigma_fine`` fine samples (zero outside);
    unchanged below 0.3 samples."""
    if sigma_fine <= 0.3:
        return w
    r = int(math.ceil(3 * sigma_fine))
    g = gaussian_window(2 * r + 1, sigma_fine, device=w.device)
    w = F.conv2d(F.pad(w[None, None], (r, r, 0, 0)), g.view(1, 1, 1, -1))
    return F.conv2d(F.pad(w, (0, 0, r, r)), g.view(1, 1, -1, 1))[0, 0]


def _reference_half_disc_kernel(coc_px: float, scale: float, softness_px: float, rim2: float, rim4: float, split: float,
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
    ss = max(_reference_fine_supersample(n), supersample | 1)
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
    w = _reference_soften(disc * prof_w * ((1.0 - sk) / 2.0 + sk * left_half), float(sigma) * ss)
    tent = (1.0 - torch.arange(-(ss - 1), ss, device=device, dtype=torch.float32).abs() / ss) / ss  # (2 ss - 1,)
    p = (ss - 1) // 2
    wp = F.pad(w[None, None], (p, p, p, p))
    out = F.conv2d(F.conv2d(wp, tent.view(1, 1, 1, -1), stride=(1, ss)), tent.view(1, 1, -1, 1), stride=(ss, 1))[0, 0]
    if beta > 0:  # pixel i holds the fine samples i ss .. i ss + ss - 1, centred on its centre like the tent's
        box = w.reshape(n, ss, n, ss).sum(dim=(1, 3)) / (ss * ss)
        out = (1.0 - beta) * out + beta * box
    return out / out.sum().clamp(min=1e-12)


# ---- scenes ---------------------------------------------------------------------------------------------

def _scene(B: int, H: int, W: int, coc_lo: float, coc_hi: float, dtype: torch.dtype, seed: int = 0) -> DPBatch:
    """Textured sharp image; CoC a smooth ramp from ``coc_lo`` to ``coc_hi`` with a near block (depth edges,
    occlusion) and a few invalid pixels."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H, dtype=dtype), torch.linspace(0, 1, W, dtype=dtype), indexing="ij")
    tex = 0.5 + 0.3 * torch.sin(23 * xx + 3 * torch.arange(3, dtype=dtype).view(3, 1, 1)) * torch.cos(17 * yy)
    sharp = (tex[None] + 0.1 * torch.rand(B, 3, H, W, generator=g, dtype=dtype)).clamp(0, 1)
    coc = (coc_lo + (coc_hi - coc_lo) * (0.7 * xx + 0.3 * yy))[None, None].expand(B, 1, H, W).clone()
    coc[:, :, H // 4 : H // 2, W // 3 : W // 2] = coc_lo + 0.13  # a near object: a depth edge in front
    coc += 0.3 * torch.rand(B, 1, H, W, generator=g, dtype=dtype)  # continuous CoC values, not on layer centres
    valid = torch.rand(B, 1, H, W, generator=g) > 0.05
    z = torch.zeros(B, dtype=dtype)
    return DPBatch(sharp=sharp, coc_px=coc, depth_mm=torch.full_like(coc, 1500.0), valid=valid, f_number=z + 2.0,
                   focus_distance_mm=z + 1500, focal_length_mm=z + 50, pixel_pitch_mm=z + 0.05,
                   focus_point_px=torch.zeros(B, 2))


TOL = 1e-4
"""Largest allowed difference to the reference, on images in [0, 1] (issue 22: outputs stay the same)."""


# ---- peers ------------------------------------------------------------------------------------------------

SMALL_TILES = {"TILE_MIN_PX": 12, "TILE_SIDE_PER_KERNEL_PX": 0, "TILES_PER_CHUNK": 3}
LAYER_PATHS = {
    "auto": {},
    "direct_and_tiles": {"FRAME_FFT_COST_RATIO": float("inf"), **SMALL_TILES},
    "direct_and_frame_fft": {"FRAME_FFT_COST_RATIO": 0.0},
    "fft_tiles_only": {"DIRECT_MAX_PX": 0, "FRAME_FFT_COST_RATIO": float("inf"), **SMALL_TILES},
    "fft_frame_only": {"DIRECT_MAX_PX": 0, "FRAME_FFT_COST_RATIO": 0.0},
}
"""Settings of peer_layers that force each convolution path (direct on a layer's box, FFT of the tiles
holding a layer's pixels, several tiles per layer and chunk, spectra accumulated on the frame grid)."""


@pytest.mark.parametrize("path", list(LAYER_PATHS))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", ["disk", "butterworth"])
def test_layered_peers_equal_reference(name: str, dtype: torch.dtype, path: str, monkeypatch: pytest.MonkeyPatch) -> None:
    for attr, value in LAYER_PATHS[path].items():
        monkeypatch.setattr(peer_layers if attr == "FRAME_FFT_COST_RATIO" else kernels, attr, value)
    b = _scene(2, 40, 56, -19.0, 26.0, dtype)
    sim, psf = ((TranslatingDiskSimulator(), translating_disk_psf) if name == "disk"
                else (ButterworthSimulator(), butterworth_psf))
    left, right = sim(b)
    ref_l, ref_r = _reference_render_layered(b.sharp, b.coc_px, b.valid, psf)
    assert left.dtype == dtype
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_layered_peers_equal_reference_with_coarser_layers() -> None:
    b = _scene(1, 32, 48, -12.0, 15.0, torch.float64, seed=3)
    left, right = render_layered(b.sharp, b.coc_px, b.valid, translating_disk_psf, step_px=2.5)
    ref_l, ref_r = _reference_render_layered(b.sharp, b.coc_px, b.valid, translating_disk_psf, step_px=2.5)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


# ---- ray tracing --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_raytrace_equals_reference(dtype: torch.dtype) -> None:
    b = _scene(2, 36, 50, -13.0, 17.0, dtype, seed=1)
    left, right = RayTracingSimulator()(b)
    ref_l, ref_r = _reference_render_raytrace(b.sharp, b.coc_px, b.valid)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_raytrace_equals_reference_with_capped_aperture_grid() -> None:
    b = _scene(1, 30, 40, -15.0, 12.0, torch.float64, seed=2)
    left, right = render_raytrace(b.sharp, b.coc_px, b.valid, max_points_side=8)
    ref_l, ref_r = _reference_render_raytrace(b.sharp, b.coc_px, b.valid, max_points_side=8)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_raytrace_equals_reference_whatever_the_thread_count() -> None:
    """Image row bands are rendered on several threads (8 bands here); the result must not depend on how many."""
    b = _scene(1, 64, 30, -9.0, 11.0, torch.float64, seed=4)
    ref_l, ref_r = _reference_render_raytrace(b.sharp, b.coc_px, b.valid)
    one = render_raytrace(b.sharp, b.coc_px, b.valid, threads=1)
    more = render_raytrace(b.sharp, b.coc_px, b.valid, threads=3)  # at most numba's pool size
    for left, right in (one, more):
        torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
        torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)
    assert torch.equal(one[0], more[0]) and torch.equal(one[1], more[1])


RAYTRACE_COCS = [0.0, 0.3, -0.7, 1.0, 1.999, 2.0, 2.001, -3.9999, 4.0, 4.0001, 5.5, -7.99, 8.0, 8.01, -9.5,
                 10.0, 13.7, -16.0001, 19.999, 23.4]
"""CoCs (px) on both sides of the even integers where the aperture grid's side steps, and beyond a cap of 8."""


@pytest.mark.parametrize("max_points_side", [8, 64])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_raytrace_equals_reference_across_grid_sides_and_the_cap(dtype: torch.dtype, max_points_side: int) -> None:
    """Every pixel its own CoC drawn from RAYTRACE_COCS (depth edges everywhere): the compiled kernel's grid
    side, mirrored rows and cut profiles must give the reference's splat for each, including capped grids whose
    rays land more than 1 px apart."""
    g = torch.Generator().manual_seed(6)
    B, H, W = 2, 40, 52
    coc = torch.tensor(RAYTRACE_COCS, dtype=dtype)[torch.randint(len(RAYTRACE_COCS), (B, 1, H, W), generator=g)]
    sharp = torch.rand(B, 3, H, W, generator=g, dtype=dtype)
    valid = torch.rand(B, 1, H, W, generator=g) > 0.05
    left, right = render_raytrace(sharp, coc, valid, max_points_side=max_points_side)
    ref_l, ref_r = _reference_render_raytrace(sharp, coc, valid, max_points_side=max_points_side)
    assert left.dtype == right.dtype == dtype
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_raytrace_equals_reference_on_a_one_pixel_wide_image() -> None:
    """A 1-px axis: rays landing beyond it are lost, as in the reference (no clamping onto the only column)."""
    b = _scene(1, 20, 1, -6.0, 7.0, torch.float64, seed=5)
    left, right = render_raytrace(b.sharp, b.coc_px, b.valid)
    ref_l, ref_r = _reference_render_raytrace(b.sharp, b.coc_px, b.valid)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


# ---- base model ---------------------------------------------------------------------------------------------

BASE_PATHS = {"auto": {}, "fft_tiles_only": {"DIRECT_MAX_PX": 0, **SMALL_TILES}}
"""Settings of neural_dp.kernels that force the base renderer's nodes through each convolution path."""


@pytest.mark.parametrize("path", list(BASE_PATHS))
@pytest.mark.parametrize("coc_range", [(-6.0, 8.0), (-30.0, 41.0)])
def test_base_layers_equal_reference(coc_range: tuple[float, float], path: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Small blurs (direct convolutions only) and large ones (FFT nodes, the node spacing ladder)."""
    for attr, value in BASE_PATHS[path].items():
        monkeypatch.setattr(kernels, attr, value)
    b = _scene(2, 48, 64, *coc_range, torch.float32, seed=4)
    model = BaseModel(rim_softness_px=0.7)
    cfg = model.config
    kfn = model._kernel_fn(0.0)
    coc = b.coc_px.float()
    left, right = render_layers(b.sharp, coc, b.valid, kfn, cfg)
    ref_l, ref_r = _reference_render_layers(b.sharp, coc, b.valid, kfn, cfg)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


@pytest.mark.parametrize("path", list(BASE_PATHS))
def test_base_layers_equal_reference_per_channel_psfs_and_cocs(path: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Per-channel kernels (a PSF component with chromatic CoCs): the 6-channel path."""
    for attr, value in BASE_PATHS[path].items():
        monkeypatch.setattr(kernels, attr, value)
    b = _scene(1, 40, 52, -20.0, 24.0, torch.float32, seed=5)
    chroma = ChromaticDefocus()
    chroma.params = {"focal_shift_r_mm": 0.4, "focal_shift_b_mm": -0.3}
    prof = PSFProfile()
    prof.params = {"rim_gain": 1.5}
    model = BaseModel(rim_softness_px=0.4, components=[chroma, prof])
    coc = torch.cat([b.coc_px + 1.5, b.coc_px, b.coc_px - 1.2], dim=1).float()
    kfn = model._kernel_fn(0.0)
    left, right = render_layers(b.sharp, coc, b.valid, kfn, model.config)
    ref_l, ref_r = _reference_render_layers(b.sharp, coc, b.valid, kfn, model.config)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


def test_base_full_disc_layers_equal_reference() -> None:
    """Symmetric kernels (the sharp frame's own blur, sharp_radiance): the right view reuses the left one."""
    from neural_dp.simulators.base.psf import full_disc_kernels

    b = _scene(2, 40, 52, -9.0, 7.0, torch.float32, seed=6)
    cfg = RenderConfig()
    kfn = lambda nodes: full_disc_kernels(nodes, cfg.supersample)  # noqa: E731
    left, right = render_layers(b.sharp, b.coc_px, b.valid, kfn, cfg)
    ref_l, ref_r = _reference_render_layers(b.sharp, b.coc_px, b.valid, kfn, cfg)
    torch.testing.assert_close(left, ref_l, atol=TOL, rtol=0)
    torch.testing.assert_close(right, ref_r, atol=TOL, rtol=0)


@pytest.mark.parametrize("node", [
    (0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0), (0.7, 1.0, 0.5, 0.0, 0.0, 1.0, 0.0), (-3.2, 1.0, 0.5, 0.0, 1.5, 1.0, 0.3),
    (12.5, 1.1, 1.2, -0.4, 0.2, 0.8, 1.0), (-41.0, 1.0, 0.5, 0.0, 0.0, 1.0, 0.0), (73.0, 1.0, 2.0, 0.0, 0.0, 0.0, 0.5),
])
def test_base_kernels_equal_reference(node: tuple[float, ...]) -> None:
    """The half-disc kernels (softening and pixel sampling now as band-matrix products) equal the
    conv2d-built ones."""
    torch.testing.assert_close(_half_disc_kernel(*node, supersample=4), _reference_half_disc_kernel(*node, supersample=4),
                               atol=1e-8, rtol=1e-5)
