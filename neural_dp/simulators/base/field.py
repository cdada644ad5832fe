"""Field coordinates of pixels: where a pixel (of a crop) sits in the full image, in [-1, 1]."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["field_coords", "field_r2"]


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
