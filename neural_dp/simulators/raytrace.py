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


SPLATS_PER_CALL = 1 << 22
"""Rays splatted per call of the bilinear adjoint (bounds the temporary grid and source copies: ~4M rays x
(2 + C + 1) floats)."""


def render_raytrace(sharp: Tensor, coc_px: Tensor, valid: Tensor, max_points_side: int = 64,
                    threads: int | None = None) -> tuple[Tensor, Tensor]:
    """Render both DP views by thin-lens ray splatting (module docstring).

    The bilinear splat of a ray is the adjoint of bilinear sampling at its landing point, so the rays are
    splatted by ATen's ``grid_sampler_2d_backward`` (bilinear, zero padding, ``align_corners=False``: grid
    -1..1 spans the pixels' outer edges, so pixel x's centre is at (2x + 1) / W - 1), which accumulates in compiled code; rays are split into ``threads``
    independent accumulators, one per batch slot of the call, so the call's threads never write the same
    plane, and the slots are summed at the end.

    Args:
        sharp: (B, C, H, W) linear image.
        coc_px: (B, 1, H, W) signed CoC diameter in px (invalid pixels are treated as in focus).
        valid: (B, 1, H, W) bool.
        max_points_side: cap on the aperture grid's side (memory/time bound for huge CoCs).
        threads: accumulators per view (default: torch's intra-op thread count).

    Returns:
        (left, right), each (B, C, H, W).
    """
    B, C, H, W = sharp.shape
    dev, dt = sharp.device, sharp.dtype
    slots = max(1, threads or torch.get_num_threads())
    c_all = torch.where(valid, coc_px, torch.zeros_like(coc_px))
    # Each pixel gets an n x n aperture grid with n >= |C| (even), so its rays land <= 1 px apart.
    n_all = torch.clamp(torch.ceil(c_all.abs()), 2, max_points_side).to(torch.int64)
    n_all = n_all + n_all % 2
    gx_per_px, gy_per_px = 2.0 / W, 2.0 / H  # grid units per px (align_corners=False)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=dt, device=dev), torch.arange(W, dtype=dt, device=dev), indexing="ij")
    gx_pix, gy_pix = ((xx + 0.5) * gx_per_px - 1).reshape(-1), ((yy + 0.5) * gy_per_px - 1).reshape(-1)
    lefts, rights = [], []
    for b in range(B):
        c, n_pix = c_all[b].reshape(-1), n_all[b].reshape(-1)
        src_all = torch.cat([sharp[b], torch.ones_like(sharp[b, :1])], 0).reshape(C + 1, H * W)
        acc = torch.zeros(2, slots, C + 1, H, W, dtype=dt, device=dev)  # (view, slot, C + coverage, H, W)
        for n in torch.unique(n_pix).tolist():
            sel = (n_pix == n).nonzero().squeeze(1)
            pts = aperture_points(int(n), dtype=dt, device=dev)
            src = src_all[:, sel] / pts.shape[0]  # (C+1, npx): each ray carries 1/N_ap of its pixel
            half_gx, half_gy = (c[sel] / 2 * gx_per_px)[None, None], (c[sel] / 2 * gy_per_px)[None, None]
            gx, gy = gx_pix[sel][None, None], gy_pix[sel][None, None]
            npx = sel.numel()
            per_slot = max(1, SPLATS_PER_CALL // (npx * slots))
            for view, side in enumerate((pts[pts[:, 0] < 0], pts[pts[:, 0] > 0])):
                for k in range(0, side.shape[0], per_slot * slots):
                    block = side[k : k + per_slot * slots]
                    used = min(slots, block.shape[0])
                    groups = block[: block.shape[0] // used * used].reshape(used, -1, 2)
                    rest = block[groups.shape[0] * groups.shape[1] :]
                    for grp in (groups, rest[None]) if rest.numel() else (groups,):
                        u, v = grp[..., 0:1], grp[..., 1:2]  # (slots, P, 1)
                        grid = torch.stack([gx + half_gx * u, gy + half_gy * v], dim=-1)  # (slots, P, npx, 2)
                        rays = src[None, :, None, :].expand(grp.shape[0], C + 1, grp.shape[1], npx)
                        target = acc[view, : grp.shape[0]]
                        splat, _ = torch.ops.aten.grid_sampler_2d_backward(rays, target, grid, 0, 0, False, [True, False])
                        target += splat
        left, right = acc[0].sum(0), acc[1].sum(0)
        cover = (left[C:] + right[C:]).clamp_min(1e-8)
        lefts.append(left[:C] / cover)
        rights.append(right[:C] / cover)
    return torch.stack(lefts), torch.stack(rights)


class RayTracingSimulator(DPSimulator):
    """Thin-lens ray tracing with the aperture discretised into points (Pan et al.'s model, re-implemented)."""

    name = "raytrace"

    def __init__(self, max_points_side: int = 64) -> None:
        super().__init__()
        self.max_points_side = max_points_side

    def forward(self, batch: DPBatch):  # type: ignore[override]
        return render_raytrace(batch.sharp, batch.coc_px, batch.valid, self.max_points_side)
