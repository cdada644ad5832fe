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
with ``n >= max |C|`` (even, so no point sits on the split), i.e. rays land at most 1 px apart.
"""

from __future__ import annotations

import math

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
    c = torch.where(valid, coc_px, torch.zeros_like(coc_px)).reshape(B, H * W)
    cmax = float(c.abs().max()) if c.numel() else 0.0
    n = min(max_points_side, max(2, math.ceil(cmax)))
    n += n % 2
    pts = aperture_points(n, dtype=sharp.dtype, device=sharp.device)
    P = pts.shape[0]
    src = torch.cat([sharp, torch.ones_like(sharp[:, :1])], dim=1).reshape(B, C + 1, H * W) / P
    yy, xx = torch.meshgrid(
        torch.arange(H, dtype=sharp.dtype, device=sharp.device),
        torch.arange(W, dtype=sharp.dtype, device=sharp.device),
        indexing="ij",
    )
    xx = xx.reshape(1, H * W)
    yy = yy.reshape(1, H * W)
    base = (torch.arange(B, device=sharp.device) * (H * W)).view(B, 1)
    flat_l = torch.zeros(C + 1, B * H * W, dtype=sharp.dtype, device=sharp.device)
    flat_r = torch.zeros_like(flat_l)
    src_flat = src.permute(1, 0, 2).reshape(C + 1, B * H * W)
    half = c / 2
    for u, v in pts.tolist():
        x = xx + half * u
        y = yy + half * v
        x0 = torch.floor(x)
        y0 = torch.floor(y)
        fx = x - x0
        fy = y - y0
        target = flat_l if u < 0 else flat_r
        for dy, dx, w in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
            xi = x0 + dx
            yi = y0 + dy
            inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
            idx = (base + (yi.clamp(0, H - 1) * W + xi.clamp(0, W - 1)).to(torch.int64)).reshape(-1)
            weight = (w * inside).reshape(1, -1)
            target.index_add_(1, idx, src_flat * weight)
    left = flat_l.reshape(C + 1, B, H, W).permute(1, 0, 2, 3)
    right = flat_r.reshape(C + 1, B, H, W).permute(1, 0, 2, 3)
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
