"""Thin-lens ray-traced DP rendering (Pan et al. 2021's peer), the reference.

A readable version of :func:`neural_dp.simulators.raytrace.render_raytrace`: every pixel's light sent through an
``n x n`` aperture grid (``n >= |CoC|``), each ray splatted bilinearly into the left or right view by the half of
the aperture it passes, normalised by the coverage, with ``torch.index_add_``. The package's version (a per-pixel
kernel compiled by numba, threads) must render the same views to 1e-4 (``tests/neural_dp/test_renderer_equivalence.py``).
Slow by design: do not optimise it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from neural_dp.simulators.raytrace import aperture_points


def render_raytrace(sharp: Tensor, coc_px: Tensor, valid: Tensor, max_points_side: int = 64) -> tuple[Tensor, Tensor]:
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
