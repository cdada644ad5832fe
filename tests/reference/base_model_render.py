"""The physical base model's occlusion-aware layered renderer and its half-disc PSF, the reference.

A readable version of :func:`neural_dp.simulators.base.render.render_layers` and of the half-disc kernel of
:mod:`neural_dp.simulators.base.psf`: the signed CoC range cut into nodes, each pixel split between its two
nodes, each node's layer blurred over the whole (padded) image, direct below ``DIRECT_MAX_PX`` taps and by FFT
above, composited front to back. The package's version (FFT only over the tiles a node touches, cached kernels)
must render the same views and kernels to 1e-4 (``tests/neural_dp/test_renderer_equivalence.py``). Slow by design:
do not optimise it.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from scipy.fft import next_fast_len
from torch import Tensor

from dp5k_learn.metrics import gaussian_window
from neural_dp.simulators.base.render import NODE_SPACING_LADDER, RenderConfig


DIRECT_MAX_PX = 9
"""Kernels at most this many taps wide are applied directly, wider ones by FFT (either path gives the same result)."""


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
    for f in NODE_SPACING_LADDER:
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


def _fine_supersample(n: int) -> int:
    return next(ss for n_max, ss in ((9, 15), (25, 7), (2**31, 5)) if n <= n_max)


def _soften(w: Tensor, sigma_fine: float) -> Tensor:
    """(N, N) fine-grid PSF convolved with a Gaussian of ``sigma_fine`` fine samples (zero outside);
    unchanged below 0.3 samples."""
    if sigma_fine <= 0.3:
        return w
    r = int(math.ceil(3 * sigma_fine))
    g = gaussian_window(2 * r + 1, sigma_fine, device=w.device)
    w = F.conv2d(F.pad(w[None, None], (r, r, 0, 0)), g.view(1, 1, 1, -1))
    return F.conv2d(F.pad(w, (0, 0, r, r)), g.view(1, 1, -1, 1))[0, 0]


def half_disc_kernel(coc_px: float, scale: float, softness_px: float, rim2: float, rim4: float, split: float,
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
