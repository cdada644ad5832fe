"""The base model's occlusion-aware layered renderer (:func:`render_layers`).

Not the peers' compositor (:mod:`neural_dp.simulators.peer_layers`): the peers quantise the CoC into hard
layers and blend them without occlusion, as Abuolaim et al. published; this one splits each pixel softly
between two CoC nodes and composites front to back, so that a near surface hides what lies behind it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ...kernels import DIRECT_MAX_PX, add_full_convolution, convolve_full

__all__ = ["RenderConfig", "render_layers", "render_layers_multi", "NODE_SPACING_LADDER"]


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
        chunk: pairs rendered at once. Each node's layer is blurred and composited over the bounding box of its
            pixels in the chunk, so one pair per chunk keeps every box to its own pair's pixels: on diagnose's
            crops (another renderer's set, 2026-12-06) a pair's own boxes were 44 % of the area of the boxes of
            4-pair chunks and 36 % of its (pair, node) layers were empty, and renders took half the time
            (0.35 s against 0.69 s for a field-varying PSF over 12 crops, one thread; the scored pixels the
            same within 4e-7). On whole 640 x 426 frames with the same depth everywhere, where a chunk's boxes
            are each pair's, one pair per chunk is no slower (0.40 s against 0.49 s on one thread, 0.38 against
            0.35 on two).
    """

    node_step_px: float = 0.25
    node_rel_step: float = 0.08
    max_nodes: int = 48
    occlude_min_px: float = 2.0
    occlude_rel: float = 0.25
    supersample: int = 4
    chunk: int = 1


NODE_SPACING_LADDER: tuple[float, ...] = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0, 64.0)
"""Factors by which :func:`_nodes` grows ``node_step_px`` and ``node_rel_step`` together, in order, until the
CoC range fits in ``max_nodes`` nodes (fixed ratios, so the node grid does not move with small CoC changes)."""


def _nodes(coc: Tensor, valid: Tensor, cfg: RenderConfig) -> Tensor:
    """(K,) CoC nodes on a fixed grid covering the valid CoC range (at least 2 nodes).

    Spacing ``max(step, rel * |c|)`` outward from 0 (``step = node_step_px``, ``rel = node_rel_step``): a
    blend of two neighbouring kernels stands in for the kernel between them, which is accurate when their
    sizes differ little relative to the blur itself; near focus, where a quarter pixel changes the blur's
    frequency response most, the steps are smallest. The grid does not move when the CoC map changes
    slightly (a fitted parameter's finite difference), so interpolation error stays constant and Jacobians
    stay clean; ``step`` and ``rel`` grow in fixed ratios only when the range needs more than ``max_nodes``.
    """
    lo = hi = math.nan
    if valid is not None:  # the extremes over the valid pixels, without gathering them (5 x faster)
        m = valid.expand_as(coc)
        lo, hi = float(torch.where(m, coc, math.inf).amin()), float(torch.where(m, coc, -math.inf).amax())
    if not lo <= hi:  # no valid pixel (or no mask): the whole map
        lo, hi = (float(x) for x in torch.aminmax(coc))
    return torch.tensor(_node_grid(lo, hi, cfg.node_step_px, cfg.node_rel_step, cfg.max_nodes), device=coc.device, dtype=torch.float32)


@functools.lru_cache(maxsize=1024)
def _node_grid(lo: float, hi: float, node_step_px: float, node_rel_step: float, max_nodes: int) -> tuple[float, ...]:
    """The nodes of :func:`_nodes` for the CoC range [lo, hi] px (cached: a fit renders the same range again)."""
    grid: list[float] = []
    for f in NODE_SPACING_LADDER:
        step, rel = node_step_px * f, node_rel_step * f
        grid = _node_side(max(hi, 0.0), step, rel)
        neg = _node_side(max(-lo, 0.0), step, rel)
        grid = [-x for x in reversed(neg[1:])] + grid
        # keep the nodes that bracket [lo, hi]
        i0 = max(0, max((i for i, x in enumerate(grid) if x <= lo), default=0))
        i1 = min(len(grid) - 1, min((i for i, x in enumerate(grid) if x >= hi), default=len(grid) - 1))
        grid = grid[i0 : max(i1, i0 + 1) + 1]
        if len(grid) <= max_nodes:
            break
    return tuple(grid)


def _node_side(extent: float, step: float, rel: float) -> list[float]:
    """Nodes 0, c1, c2, ... with ``c_{k+1} = c_k + max(step, rel c_k)`` until one reaches ``extent``."""
    out = [0.0]
    while out[-1] <= extent:
        out.append(out[-1] + max(step, rel * out[-1]))
    return out


def _support(k: Tensor, tol: float = 1e-7) -> int:
    """Half-width (px) of the centred square holding every entry of ``k`` (..., n, n) above ``tol``."""
    return _supports(k[None], tol)[0]


def _supports(kl: Tensor, tol: float = 1e-7) -> list[int]:
    """:func:`_support` of each of K kernels ``kl`` (K, ..., n, n), in one pass."""
    K, n = kl.shape[0], kl.shape[-1]
    h = n // 2
    nz = (kl.abs() > tol).reshape(K, -1, n, n).any(1)  # (K, n, n)
    dist = (torch.arange(n, device=kl.device) - h).abs()
    rows = torch.where(nz.any(2), dist.view(1, n), -1).amax(1)  # farthest row holding an entry, -1 for none
    cols = torch.where(nz.any(1), dist.view(1, n), -1).amax(1)
    return torch.maximum(rows, cols).clamp(min=0).tolist()


def _fractional_index(coc: Tensor, nodes: Tensor) -> Tensor:
    """Fractional node index of each CoC value: ``k + (c - c_k) / (c_{k+1} - c_k)`` for the bracketing
    nodes (values outside the nodes' range clamp to its ends)."""
    K = nodes.shape[0]
    c = coc.clamp(float(nodes[0]), float(nodes[-1])).contiguous()
    i = (torch.searchsorted(nodes, c.reshape(-1), right=True) - 1).clamp(0, K - 2).reshape(c.shape)
    lo, hi = nodes[i], nodes[i + 1]
    return i.float() + (c - lo) / (hi - lo)


def _node_boxes(t: Tensor, K: int) -> dict[int, tuple[int, int, int, int]]:
    """Bounding box ``(y0, y1, x0, x1)`` (px, ends exclusive) of the pixels with a positive weight on each node,
    from their fractional node index ``t`` (B, Cc, H, W), over batch and channels; nodes without any are left
    out. A pixel with index ``t`` weighs on nodes ``floor(t)`` and ``ceil(t)``."""
    H, W = t.shape[-2:]
    t = t.detach().cpu()
    lo = torch.floor(t).clamp(0, K - 1).to(torch.int64)
    hi = torch.ceil(t).clamp(0, K - 1).to(torch.int64)
    rows = torch.arange(H).view(1, 1, H, 1).expand_as(lo).reshape(-1)
    cols = torch.arange(W).view(1, 1, 1, W).expand_as(lo).reshape(-1)
    idx = torch.cat([lo.reshape(-1), hi.reshape(-1)])
    rows, cols = torch.cat([rows, rows]), torch.cat([cols, cols])
    y0 = torch.full((K,), H).scatter_reduce(0, idx, rows, "amin")
    y1 = torch.full((K,), -1).scatter_reduce(0, idx, rows, "amax")
    x0 = torch.full((K,), W).scatter_reduce(0, idx, cols, "amin")
    x1 = torch.full((K,), -1).scatter_reduce(0, idx, cols, "amax")
    return {k: (a, b + 1, c, d + 1) for k, (a, b, c, d) in enumerate(zip(y0.tolist(), y1.tolist(), x0.tolist(), x1.tolist()))
            if b >= 0}


SYMMETRY_TOL = 1e-6
"""A kernel whose hflip differs from it by at most this fraction of its peak is symmetric (full discs, the
in-focus node): its right view equals its left one and is not convolved again."""


def render_layers(sharp: Tensor, coc: Tensor, valid: Tensor, kernel_fn, cfg: RenderConfig,
                  views: tuple[str, ...] = ("l", "r")) -> tuple[Tensor | None, Tensor | None]:
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

    Work per node is confined to where it has members: its layer is blurred over its bounding box
    (directly for small kernels, by FFTs of the tiles holding its pixels for large ones,
    :func:`neural_dp.kernels.add_full_convolution`) and composited over that box grown by the kernel's
    support, outside which its blur is zero.

    Args:
        sharp: (B, 3, H, W) linear sharp image.
        coc: (B, Cc, H, W), Cc in {1, 3}: signed CoC per pixel (per colour channel), px.
        valid: (B, 1, H, W) bool; only used to choose the node range.
        kernel_fn: ``nodes (K,) -> (K, Ck, n, n)`` left-view kernels, Ck in {1, 3}.
        cfg: discretisation.
        views: the views to render, ``"l"`` and/or ``"r"`` (each is computed apart from the other: one alone is
            the same as with both up to float32 rounding, at about half the cost; the FFT path transforms a
            different batch of kernels, the direct one gives the same bits).

    Returns:
        left, right: (B, 3, H, W), each ``H * sharp`` (PSFs sum to 1; no factor 1/2 yet); None for a view not
        rendered.
    """
    return render_layers_multi(sharp, coc, valid, [(kernel_fn, views)], cfg)[0]


KernelSet = tuple[Callable[[Tensor], Tensor], tuple[str, ...]]
"""A ``kernel_fn`` (as in :func:`render_layers`) and the views to render with it."""


class _Composite:
    """The front-to-back compositing state of the kernel sets of one alpha layout over a chunk of ``nb`` pairs
    (:func:`render_layers_multi`): their views' accumulated colour (nb, V, 3, H, W), coverage and transmittance
    (nb, V, nc, H, W), V every view of every set, stacked so that a node updates them all in one operation, and
    the alphas not yet applied as occluders."""

    def __init__(self, plan: "_Plan", s: Tensor) -> None:
        nb, _, H, W = s.shape
        self.plan = plan
        self.acc = s.new_zeros(nb, plan.views, 3, H, W)
        self.cov = s.new_zeros(nb, plan.views, plan.nc, H, W)
        self.trans = s.new_ones(nb, plan.views, plan.nc, H, W)
        self.pending: list[tuple[float, tuple[int, int, int, int], Tensor]] = []


@dataclass
class _Plan:
    """The kernel sets of one alpha layout, convolved and composited together (:func:`render_layers_multi`).

    Attributes:
        members: per kernel set, its index in the call and its views' stacked indices (by view name).
        views: how many views are stacked.
        per_channel: one alpha channel per colour (the CoC or the kernels differ by colour), else one.
        support: per node, the largest support (px) of the sets' kernels (each set's kernel is zero beyond its own).
        psfs: per node, the PSFs of every set's views, (V', k, k) or (V', 3 + nc, k, k), cropped to ``support``;
            V' < ``views`` where a symmetric kernel serves both views of its set.
        index: per node, the PSF of each stacked view (None: the PSFs are the views, in order).
    """

    members: list[tuple[int, dict[str, int]]]
    views: int
    per_channel: bool
    support: list[int]
    psfs: list[Tensor]
    index: list[Tensor | None]

    @property
    def nc(self) -> int:
        return 3 if self.per_channel else 1


def _plan(sets: list[tuple[int, tuple[str, ...], Tensor]], per_channel: bool, K: int) -> _Plan:
    """The :class:`_Plan` of the kernel sets ``(index, views, kernels (K, Ck, n, n))`` of one alpha layout."""
    nc = 3 if per_channel else 1
    supports = [_supports(kl) for _, _, kl in sets]
    members, offset = [], 0
    for i, views, _ in sets:
        members.append((i, {v: offset + j for j, v in enumerate(views)}))
        offset += len(views)
    support, psfs, index = [], [], []
    for k in range(K):
        sup = max(sp[k] for sp in supports)
        parts: list[Tensor] = []
        idx: list[int] = []
        for _, views, kl in sets:
            ker = kl[k]
            h = ker.shape[-1] // 2
            if h < sup:  # another set's kernel reaches farther: zeros around this one
                ker = F.pad(ker, (sup - h,) * 4)
            p = _view_psfs(ker, sup, 3 + nc, views)
            first = sum(q.shape[0] for q in parts)
            idx += [first + (j if p.shape[0] > 1 else 0) for j in range(len(views))]
            parts.append(p)
        if any(q.ndim == 4 for q in parts):  # a set with one kernel for every channel beside per-colour ones
            parts = [q if q.ndim == 4 else q[:, None].expand(-1, 3 + nc, -1, -1) for q in parts]
        support.append(sup)
        psfs.append(torch.cat(parts))
        index.append(None if idx == list(range(len(idx))) and len(idx) == psfs[-1].shape[0] else torch.tensor(idx, device=kl.device))
    return _Plan(members, offset, per_channel, support, psfs, index)


def render_layers_multi(sharp: Tensor, coc: Tensor, valid: Tensor, kernel_sets: Sequence[KernelSet], cfg: RenderConfig
                        ) -> list[tuple[Tensor | None, Tensor | None]]:
    """:func:`render_layers` of one scene with several kernel sets (a PSF that changes over the field, rendered
    at each field node): the CoC nodes, the pixels' split between them and each node's layer are computed once,
    and the layer is blurred with every view of every set in one convolution (each set's kernels zero-padded to
    the largest support among them) and composited in one stacked state. Each set's views are those of
    :func:`render_layers` with that set alone up to float32 rounding (2e-7 on diagnose's crops: a kernel's zero
    border and the FFT's batch change the order of sums); with one set, the same to the bit. On diagnose's crops
    of a field-varying PSF (another renderer, one thread) this is 12-20 % faster than rendering the nine sets
    apart over the shared layers.

    Returns:
        one (left, right) per kernel set, each (B, 3, H, W) or None for a view the set does not render.
    """
    B, _, H, W = sharp.shape
    if coc.shape[1] == 3 and bool((coc[:, 1:] == coc[:, :1]).all()):
        coc = coc[:, :1]  # one CoC for all colours (a chromatic defocus held at zero): the same render, 4 channels not 6
    nodes = _nodes(coc, valid, cfg)
    K = nodes.shape[0]
    t = _fractional_index(coc, nodes)  # (B, Cc, H, W)
    node_c = [float(c) for c in nodes]
    layouts: dict[bool, list[tuple[int, tuple[str, ...], Tensor]]] = {}
    for i, (kernel_fn, views) in enumerate(kernel_sets):
        kl = kernel_fn(nodes)  # (K, Ck, n, n)
        layouts.setdefault(kl.shape[1] == 3 or coc.shape[1] == 3, []).append((i, tuple(views), kl))
    plans = [_plan(sets, per_channel, K) for per_channel, sets in layouts.items()]

    def occludes(c_near: float, c_far: float) -> bool:
        return c_far - c_near > max(cfg.occlude_min_px, cfg.occlude_rel * max(abs(c_near), abs(c_far)))

    outs: list[list[Tensor]] = [[] for _ in plans]  # per plan, per chunk: the stacked views (nb, V, 3, H, W)
    for b0 in range(0, B, cfg.chunk):
        s = sharp[b0 : b0 + cfg.chunk]
        tt = t[b0 : b0 + cfg.chunk]
        nb = s.shape[0]
        boxes = _node_boxes(tt, K)
        states = [_Composite(plan, s) for plan in plans]
        for k in range(K):
            if k not in boxes:
                continue
            y0, y1, x0, x1 = boxes[k]
            m = (1.0 - (tt[..., y0:y1, x0:x1] - k).abs()).clamp(min=0.0)  # (nb, Cc, h, w) soft membership
            for st in states:
                plan = st.plan
                group = [p for p in st.pending if occludes(p[0], node_c[k])]
                if group:
                    _occlude(st.trans, group)
                    st.pending = [p for p in st.pending if not occludes(p[0], node_c[k])]
                mm = m.expand(nb, 3, *m.shape[-2:]) if plan.per_channel else m
                sig = torch.cat([s[..., y0:y1, x0:x1] * mm, mm], dim=1)  # (nb, 3 + nc, h, w)
                nc, sup, psfs = plan.nc, plan.support[k], plan.psfs[k]
                # (nb, V', 3 + nc, ...): one blur per PSF (a symmetric kernel's serves both views of its set)
                if 2 * sup + 1 <= DIRECT_MAX_PX:
                    full = convolve_full(sig, psfs)  # what add_full_convolution adds to zeros, without them
                else:
                    full = sig.new_zeros(nb, psfs.shape[0], 3 + nc, y1 - y0 + 2 * sup, x1 - x0 + 2 * sup)
                    occupied = (m > 0).flatten(0, 1).any(0)  # (h, w): the FFT path skips tiles without members
                    add_full_convolution(full, 0, 0, sig, psfs, occupied)
                # the blur covers the box grown by the support, clipped to the frame
                ry0, ry1, rx0, rx1 = max(y0 - sup, 0), min(y1 + sup, H), max(x0 - sup, 0), min(x1 + sup, W)
                full = full[..., ry0 - (y0 - sup) : ry1 - (y0 - sup), rx0 - (x0 - sup) : rx1 - (x0 - sup)]
                if plan.index[k] is not None:
                    full = full.index_select(1, plan.index[k])  # (nb, V, 3 + nc, ...)
                col, alpha = full[:, :, :3], full[:, :, 3 : 3 + nc].clamp(0.0, 1.0)
                tr = st.trans[..., ry0:ry1, rx0:rx1]
                st.acc[..., ry0:ry1, rx0:rx1] += tr * col
                st.cov[..., ry0:ry1, rx0:rx1] += tr * alpha
                st.pending.append((node_c[k], (ry0, ry1, rx0, rx1), alpha))
        for out, st in zip(outs, states):
            out.append(st.acc / st.cov.clamp(min=1e-6))
    result: list[tuple[Tensor | None, Tensor | None]] = [(None, None)] * len(kernel_sets)
    for plan, out in zip(plans, outs):
        stacked = torch.cat(out)  # (B, V, 3, H, W)
        for i, where in plan.members:
            result[i] = (stacked[:, where["l"]] if "l" in where else None, stacked[:, where["r"]] if "r" in where else None)
    return result


def _view_psfs(kernel: Tensor, support: int, channels: int, views: tuple[str, ...] = ("l", "r")) -> Tensor:
    """The left kernel ``kernel`` (Ck, n, n) cropped to ``support`` and its hflip (the right kernel), for the
    ``views`` in that order, as PSFs for :func:`neural_dp.kernels.add_full_convolution`: (V, n', n') shared by all
    channels (Ck = 1) or (V, channels, n', n') per channel (Ck = 3: colour, then alpha), with V = 1 when the
    kernel is symmetric (:data:`SYMMETRY_TOL`; the right view is then the left one)."""
    h = kernel.shape[-1] // 2
    kv = kernel[..., h - support : h + support + 1, h - support : h + support + 1]
    symmetric = float((kv - kv.flip(-1)).abs().max()) <= SYMMETRY_TOL * float(kv.abs().max())
    ks = [kv] if symmetric else [kv if v == "l" else kv.flip(-1) for v in views]
    if kv.shape[0] == 1:
        return torch.stack([k[0] for k in ks])
    return torch.stack([torch.cat([k, k], 0)[:channels] for k in ks])


def _occlude(trans: Tensor, group: list[tuple[float, tuple[int, int, int, int], Tensor]]) -> None:
    """Multiply the views' transmittance ``trans`` (nb, V, nc, H, W) by ``clip(1 - sum of the group's alphas, 0,
    1)`` (in place), over the union of the group's regions (``(y0, y1, x0, x1)`` each; the alphas, (nb, V or 1,
    nc, h, w), are zero outside them)."""
    uy0, uy1 = min(p[1][0] for p in group), max(p[1][1] for p in group)
    ux0, ux1 = min(p[1][2] for p in group), max(p[1][3] for p in group)
    total = trans.new_zeros(*trans.shape[:3], uy1 - uy0, ux1 - ux0)
    for _, (y0, y1, x0, x1), alpha in group:
        total[..., y0 - uy0 : y1 - uy0, x0 - ux0 : x1 - ux0] += alpha
    trans[..., uy0:uy1, ux0:ux1] *= (1.0 - total).clamp(0.0, 1.0)
