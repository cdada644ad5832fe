"""Layered rendering of the handcrafted peers (translating disk, Butterworth), the reference.

A readable version of :func:`neural_dp.simulators.peer_layers.render_layered`: the CoC map cut into layers one
CoC pixel apart, each layer's premultiplied colour and coverage convolved with its PSF over the whole image (direct
or FFT by kernel size, :func:`convolve_same`), normalised by the coverage. The package's version (each layer only
over the tiles it touches, spectra accumulated on the frame grid, several convolution paths) must render the same
views to 1e-4 (``tests/neural_dp/test_renderer_equivalence.py``). Slow by design: do not optimise it.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from dp5k_common.errors import BadInputError
from neural_dp.simulators.peer_layers import PsfFn


def convolve_same(x: Tensor, psf: Tensor, *, fft_above: int = 21) -> Tensor:
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
        blur_l = convolve_same(stack, psf_l)
        blur_r = convolve_same(stack, psf_r)
        num_l += blur_l[:, :C]
        num_r += blur_r[:, :C]
        cover += blur_l[:, C:] + blur_r[:, C:]
    cover = cover.clamp_min(1e-8)
    return num_l / cover, num_r / cover
