r"""Ray tracing through a thin lens discretised into points (after Pan et al., CVPR 2021).

Pan et al.'s simulator is closed (encrypted P-code), so this follows the paper's description: the
aperture of a thin lens is discretised into a regular grid of points; every scene pixel sends one ray
through each aperture point and the ray lands on the sensor displaced from the pixel's in-focus image by

.. math::
    \Delta(u, v) = \frac{C}{2} (u, v), \qquad u^2 + v^2 \le 1

(:math:`C` the signed CoC diameter in px, :math:`(u, v)` the normalised aperture position). Each DP
photodiode sees half of the aperture: the left view collects the rays with :math:`u < 0`, the right view
those with :math:`u > 0`. For C > 0 the left view's light therefore lands on the left half of the disc and
for C < 0 on the right half (docs/conventions.md), and the right PSF is the hflip of the left one.

Every ray carries :math:`1/N_{ap}` of its pixel's energy and is splatted bilinearly; the views are divided
by the accumulated coverage of all rays (1 in the interior of a region of constant CoC), which fills the
gaps that forward splatting leaves at depth edges and at the image border. The grid has ``n x n`` points
with ``n >= |C|`` chosen per pixel (even, so no point sits on the split), i.e. a pixel's rays land at most
1 px apart while small blurs stay cheap.
"""

from __future__ import annotations


import torch
from torch import Tensor

from ..batch import DPBatch
from .interface import DPSimulator


def aperture_points(n: int, *, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
    """Centres of an ``n x n`` grid over [-1, 1]^2 that fall inside the unit disk. Returns (P, 2) as (u, v)."""
    t = (torch.arange(n, dtype=dtype, device=device) + 0.5) / n * 2 - 1
    v, u = torch.meshgrid(t, t, indexing="ij")
    keep = u**2 + v**2 <= 1.0
    return torch.stack([u[keep], v[keep]], dim=1)


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


class RayTracingSimulator(DPSimulator):
    """Thin-lens ray tracing with the aperture discretised into points (Pan et al.'s model, re-implemented)."""

    name = "raytrace"

    def __init__(self, max_points_side: int = 64) -> None:
        super().__init__()
        self.max_points_side = max_points_side

    def forward(self, batch: DPBatch):  # type: ignore[override]
        return render_raytrace(batch.sharp, batch.coc_px, batch.valid, self.max_points_side)
