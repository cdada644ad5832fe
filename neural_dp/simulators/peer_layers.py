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
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from scipy.fft import next_fast_len
from torch import Tensor

from .. import kernels
from ..kernels import add_full_convolution, fft_grid, tile_occupancy, tile_shape_px

PsfFn = Callable[[float], NDArray[np.float64]]
"""Maps a layer's signed CoC diameter (px) to its LEFT-view PSF (k x k, k odd, sum 1/2, convolution form)."""

FRAME_FFT_COST_RATIO = 1.0
"""A large-kernel layer is convolved tile by tile (only the tiles holding its pixels,
:func:`neural_dp.kernels.add_full_convolution`) when that costs less than this many times accumulating its
spectrum on the frame's FFT grid. Estimated cost in channel transforms of the grid's area: a tile costs a
forward and two inverse FFTs (:data:`TILE_FFT_CHANNELS`), a frame layer a forward FFT and its spectrum
products (:data:`FRAME_FFT_CHANNELS`)."""

TILE_FFT_CHANNELS = 12.0
FRAME_FFT_CHANNELS = 6.5


@dataclass
class _Box:
    """A layer's bounding box over the batch: rows ``y0:y1``, columns ``x0:x1`` (px, end exclusive)."""

    y0: int
    y1: int
    x0: int
    x1: int


def quantize_coc(coc_px: Tensor, valid: Tensor, step_px: float) -> Tensor:
    """Layer index per pixel: ``round(C / step)``; invalid pixels go to the in-focus layer 0. Returns int64."""
    c = torch.where(valid, coc_px, torch.zeros_like(coc_px))
    return torch.round(c / step_px).to(torch.int64)


def _layer_boxes(levels: Tensor) -> dict[int, _Box]:
    """Bounding box of every layer index in ``levels`` (B, 1, H, W), over all images of the batch."""
    H, W = levels.shape[-2:]
    ids, inverse = torch.unique(levels, return_inverse=True)
    inv = inverse.reshape(-1, H, W)
    n = ids.numel()
    rows = torch.arange(H).view(1, H, 1).expand_as(inv).reshape(-1)
    cols = torch.arange(W).view(1, 1, W).expand_as(inv).reshape(-1)
    flat = inv.reshape(-1)
    lo_y = torch.full((n,), H).scatter_reduce(0, flat, rows, "amin")
    hi_y = torch.full((n,), -1).scatter_reduce(0, flat, rows, "amax")
    lo_x = torch.full((n,), W).scatter_reduce(0, flat, cols, "amin")
    hi_x = torch.full((n,), -1).scatter_reduce(0, flat, cols, "amax")
    return {int(i): _Box(int(a), int(b) + 1, int(c), int(d) + 1)
            for i, a, b, c, d in zip(ids.tolist(), lo_y.tolist(), hi_y.tolist(), lo_x.tolist(), hi_x.tolist())}


def _embedded_spectrum(psf: Tensor, Hp: int, Wp: int) -> Tensor:
    """rfft2 of a (k, k) PSF placed with its centre at (0, 0) of an (Hp, Wp) grid (wrapped)."""
    k = psf.shape[-1]
    big = psf.new_zeros(Hp, Wp)
    big[:k, :k] = psf
    return torch.fft.rfft2(torch.roll(big, shifts=(-(k // 2), -(k // 2)), dims=(0, 1)))


def _hflip_spectrum(spec: Tensor) -> Tensor:
    r"""Spectrum of the hflip (x -> -x about the centre) of a real PSF from its rfft2 ``spec`` (Hp, Wf):
    :math:`\hat K_r(v, u) = \overline{\hat K_l(-v, u)}`."""
    return torch.roll(spec.flip(-2), shifts=1, dims=-2).conj()


def render_layered(sharp: Tensor, coc_px: Tensor, valid: Tensor, left_psf: PsfFn, step_px: float = 1.0) -> tuple[Tensor, Tensor]:
    """Render both DP views by depth layers with coverage normalisation (module docstring).

    Each layer is convolved only where it has members (:func:`neural_dp.kernels.add_full_convolution`):
    within its bounding box by direct convolution (small kernels) or by FFTs of the tiles that hold its
    pixels; a layer spread over so many tiles that this would cost more has its spectrum accumulated on the
    frame's FFT grid instead, and all such layers share one inverse FFT per view. All are the same linear
    convolution (zero padding at the image border).

    Args:
        sharp: (B, C, H, W) linear image.
        coc_px: (B, 1, H, W) signed CoC diameter in px.
        valid: (B, 1, H, W) bool.
        left_psf: layer PSF generator (the right PSF is its horizontal flip).
        step_px: layer spacing in CoC diameter px (1 px: layers at every integer CoC, as Abuolaim et al.
            round the CoC to integers).

    Returns:
        (left, right), each (B, C, H, W). Each image is rendered on its own (its own layers, boxes and FFT
        grid), so an image renders the same whatever other images share its batch: a synthesis split over
        ranks writes the same pairs as one process.
    """
    B, C, H, W = sharp.shape
    if B > 1:
        views = [render_layered(sharp[i : i + 1], coc_px[i : i + 1], valid[i : i + 1], left_psf, step_px) for i in range(B)]
        return torch.cat([v[0] for v in views]), torch.cat([v[1] for v in views])
    levels = quantize_coc(coc_px, valid, step_px)
    dt, dev = sharp.dtype, sharp.device
    boxes = _layer_boxes(levels.cpu())
    psfs = {lv: torch.as_tensor(np.ascontiguousarray(left_psf(lv * step_px)), dtype=dt, device=dev) for lv in boxes}
    r = max(p.shape[-1] for p in psfs.values()) // 2
    Hp, Wp = next_fast_len(H + 2 * r, real=True), next_fast_len(W + 2 * r, real=True)
    # accumulators with an r-px margin: each layer's full convolution lands inside them
    acc = sharp.new_zeros(B, 2, C + 1, H + 2 * r, W + 2 * r)  # (view, colour + coverage)
    spec: Tensor | None = None  # frame-grid spectra of the layers accumulated there, (B, 2, C + 1, Hp, Wf)
    for level, box in boxes.items():
        psf = psfs[level]
        k = psf.shape[-1]
        h, w = box.y1 - box.y0, box.x1 - box.x0
        mask = (levels[..., box.y0 : box.y1, box.x0 : box.x1] == level).to(dt)
        stack = torch.cat([sharp[..., box.y0 : box.y1, box.x0 : box.x1] * mask, mask], dim=1)  # (B, C + 1, h, w)
        y0, x0 = box.y0 + r - k // 2, box.x0 + r - k // 2  # where the full convolution of the box starts in acc
        occupied = mask.amax((0, 1)) > 0  # (h, w)
        tile = tile_shape_px(h, w, k)
        n_tiles = int(tile_occupancy(occupied, tile).sum())
        gy, gx = fft_grid(tile, k)
        tiles_cost = TILE_FFT_CHANNELS * n_tiles * gy * gx
        if k <= kernels.DIRECT_MAX_PX or tiles_cost < FRAME_FFT_COST_RATIO * FRAME_FFT_CHANNELS * Hp * Wp:
            add_full_convolution(acc, y0, x0, stack, torch.stack([psf, psf.flip(1)]), occupied)
            continue
        frame = F.pad(stack, (box.x0 + r, Wp - box.x1 - r, box.y0 + r, Hp - box.y1 - r))
        X = torch.fft.rfft2(frame)  # (B, C + 1, Hp, Wf)
        Kl = _embedded_spectrum(psf, Hp, Wp)
        Kr = _hflip_spectrum(Kl)
        if spec is None:
            spec = X.new_zeros(B, 2, C + 1, *X.shape[-2:])
        spec[:, 0].addcmul_(X, Kl)
        spec[:, 1].addcmul_(X, Kr)
    if spec is not None:
        acc += torch.fft.irfft2(spec, s=(Hp, Wp))[..., : H + 2 * r, : W + 2 * r]
    acc = acc[..., r : r + H, r : r + W]
    cover = (acc[:, 0, C:] + acc[:, 1, C:]).clamp_min(1e-8)
    return acc[:, 0, :C] / cover, acc[:, 1, :C] / cover
