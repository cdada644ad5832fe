"""Undoing the sharp frame's own blur: the all-in-focus radiance behind an f/22 (or any N_s) capture."""

from __future__ import annotations

from dataclasses import astuple

import torch
from torch import Tensor

from dp5k_common.dataset import SHARP_F_NUMBER
from dp5k_learn.batch import DPBatch

from .cache import TensorCache
from .psf import full_disc_kernels
from .render import RenderConfig, render_layers

__all__ = ["sharp_blur_coc_px", "sharp_radiance"]


_RADIANCE_CACHE = TensorCache(256 * 2**20)
"""Deblurred sharp frames by their batch's sharp, CoC and sharp f-number tensors (kept alive by the entries),
bounded by the radiances' total size."""


def sharp_blur_coc_px(batch: DPBatch) -> Tensor:
    r"""(B, 1, H, W) signed CoC diameter of the sharp frame's own blur, output px.

    Eq. 6 is proportional to :math:`1/N` at fixed focus, so the sharp frame, taken at :math:`N_s` with the
    same focus, blurs each point by :math:`C_s = C \, N / N_s` (``C`` = ``batch.coc_px``, the DP capture's
    CoC). :math:`N_s` is ``batch.sharp_f_number`` (:data:`SHARP_F_NUMBER` when absent); :math:`N_s = 0`
    marks an all-in-focus sharp image (:math:`C_s = 0`).
    """
    B = batch.sharp.shape[0]
    ns = batch.sharp_f_number if batch.sharp_f_number is not None else torch.full((B,), SHARP_F_NUMBER)
    ns = ns.to(batch.coc_px.device, torch.float32)
    ratio = torch.where(ns > 0, batch.f_number.float() / ns.clamp(min=1e-6), torch.zeros_like(ns))
    return batch.coc_px.float() * ratio.view(B, 1, 1, 1)


def sharp_radiance(batch: DPBatch, iters: int = 2, config: RenderConfig | None = None) -> Tensor:
    r"""(B, 3, H, W) the all-in-focus radiance behind the sharp frame, linear, the sharp frame's scale.

    The sharp frame :math:`s` is a capture at :math:`N_s` (f/22), blurred per pixel by a disc of diameter
    :math:`|C_s|` (:func:`sharp_blur_coc_px`): :math:`s = B x`, with :math:`B` the same occlusion-aware
    layered blur the model renders with (full disc). Van Cittert iterations undo it:
    :math:`x_0 = s,\ x_{k+1} = x_k + (s - B x_k)`. At f/2.8 the sharp frame's disc is 13 % of the DP
    capture's; treating the frame as a pinhole image leaves a rim-softening error 3-25 x the renderer's own
    on a slanted plane (docs/diagnose.md, base model); one iteration removes about 90 % of it, two reach the
    renderer's floor. Discs under 2.4 px keep :math:`|1 - \hat B| < 1` below Nyquist, so the iteration
    converges where the DP blur lets detail through. ``iters = 0`` returns ``s``. Results are cached per
    (sharp, coc, sharp f-numbers) tensors and their in-place versions, iterations and discretisation: fits render the same batch many
    times (:data:`_RADIANCE_CACHE` is bounded in bytes).
    """
    if iters <= 0 or batch.sharp_f_number is not None and bool((batch.sharp_f_number <= 0).all()):
        return batch.sharp.float()
    cfg = config or RenderConfig()
    versions = tuple(t._version for t in (batch.sharp, batch.coc_px, batch.valid, batch.sharp_f_number) if t is not None)
    key = (id(batch.sharp), id(batch.coc_px), id(batch.sharp_f_number), versions, int(iters), astuple(cfg))
    sources = (batch.sharp, batch.coc_px, batch.sharp_f_number)
    hit = _RADIANCE_CACHE.get(key, sources)
    if hit is not None:
        return hit
    s = batch.sharp.float()
    coc_s = sharp_blur_coc_px(batch)

    def blur(x: Tensor) -> Tensor:
        return render_layers(x, coc_s, batch.valid, lambda nodes: full_disc_kernels(nodes, cfg.supersample), cfg)[0]

    x = s
    for _ in range(iters):
        x = x + (s - blur(x))
    _RADIANCE_CACHE.put(key, sources, x)
    return x
