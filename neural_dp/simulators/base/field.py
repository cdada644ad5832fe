"""Field coordinates of pixels: where a pixel (of a crop) sits in the full image, in [-1, 1]."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["field_coords", "field_r2", "field_y_units"]


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


def field_y_units(field: Tensor) -> Tensor:
    """(B,) each item's full image half-height in units of its half-width, ``(H_f - 1) / (W_f - 1)``, read from
    the field coordinates' steps per pixel (``2 / (W_f - 1)`` along x, ``2 / (H_f - 1)`` along y): field y times
    it is the same point's y on the sensor in the unit of field x. ``field``: (B, 2, H, W); 1 where a crop is
    under 2 px along either axis."""
    B, _, H, W = field.shape
    ones = field.new_ones(B)
    if W < 2 or H < 2:
        return ones
    step_x = field[:, 0, 0, 1] - field[:, 0, 0, 0]
    step_y = field[:, 1, 1, 0] - field[:, 1, 0, 0]
    return torch.where(step_y > 0, step_x / step_y.clamp(min=1e-12), ones)
