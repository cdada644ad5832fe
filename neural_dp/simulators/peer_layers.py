r"""The peers' compositor: depth-layer discretisation and blending shared by the translating-disk and
Butterworth peers. (The base model has its own, occlusion-aware one: :mod:`neural_dp.simulators.base.render`;
the peers keep this one because it is how they were published.)

The paper (Sec. 5.2.1) renders both handcrafted PSF families with the Butterworth simulator's scheme:
quantise the signed CoC into layers, blur each layer with that layer's left/right PSF and blend. We blend
*mask-then-blur* and normalise by the accumulated coverage:

.. math::
    I_l = \frac{\sum_k H^l_k * (M_k I_s)}{\sum_k (H^l_k + H^r_k) * M_k}, \qquad
    I_r = \frac{\sum_k H^r_k * (M_k I_s)}{\sum_k (H^l_k + H^r_k) * M_k}

where :math:`M_k` is layer k's indicator and each view PSF sums to 1/2 (so :math:`I_l + I_r` is the
full-aperture blur and a uniform region keeps its brightness). Without the denominator, every layer
boundary loses the light its neighbours' kernels spread across it and shows a dark seam; the same
denominator also renormalises the image border (zero padding). Abuolaim et al.'s released code blurs the
whole image per layer and masks *after* blurring (no seams, but no light crosses a depth edge either);
the coverage-normalised form keeps light crossing layer boundaries, which is what defocus does.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from ..kernels import convolve_same

PsfFn = Callable[[float], NDArray[np.float64]]
"""Maps a layer's signed CoC diameter (px) to its LEFT-view PSF (k x k, k odd, sum 1/2, convolution form)."""


def quantize_coc(coc_px: Tensor, valid: Tensor, step_px: float) -> Tensor:
    """Layer index per pixel: ``round(C / step)``; invalid pixels go to the in-focus layer 0. Returns int64."""
    c = torch.where(valid, coc_px, torch.zeros_like(coc_px))
    return torch.round(c / step_px).to(torch.int64)


def render_layered(sharp: Tensor, coc_px: Tensor, valid: Tensor, left_psf: PsfFn, step_px: float = 1.0) -> tuple[Tensor, Tensor]:
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
    levels = quantize_coc(coc_px, valid, step_px)
    C = sharp.shape[1]
    num_l = torch.zeros_like(sharp)
    num_r = torch.zeros_like(sharp)
    cover = torch.zeros_like(sharp[:, :1])
    for level in torch.unique(levels).tolist():
        mask = (levels == level).to(sharp.dtype)
        stack = torch.cat([sharp * mask, mask], dim=1)
        psf_l = torch.as_tensor(np.ascontiguousarray(left_psf(level * step_px)), dtype=sharp.dtype, device=sharp.device)
        psf_r = psf_l.flip(1)
        blur_l = convolve_same(stack, psf_l)
        blur_r = convolve_same(stack, psf_r)
        num_l += blur_l[:, :C]
        num_r += blur_r[:, :C]
        cover += blur_l[:, C:] + blur_r[:, C:]
    cover = cover.clamp_min(1e-8)
    return num_l / cover, num_r / cover
