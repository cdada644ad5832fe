r"""Translating-disk DP PSF (Punnappurath, Abuolaim, Afifi, Brown, ICCP 2020).

Their kernel (``solver_translating_disk_kernel.m``) sums a disk times copies of itself translated along x:
:math:`h = \sum_{i \ge 0} D \cdot D(\cdot - i\,\mathrm{sign}(s))`. Each pixel of the disk is thereby
weighted by the number of shifted copies still covering it, i.e. by its distance along its row to the
disk's edge. In the continuous limit, for a disk of radius :math:`r` centred at 0,

.. math::
    H_l(x, y) \propto D_r(x, y) \left(\sqrt{r^2 - y^2} - \mathrm{sign}(C)\, x\right), \qquad
    H_r = \mathrm{hflip}(H_l), \qquad \sum H_l = \sum H_r = 1/2

a disk times a linear ramp along x in every row. In dp5k's convention (docs/conventions.md) a point behind
focus (C > 0) lands on the LEFT half of its disc in the left view, so the left ramp rises toward -x for
C > 0 and toward +x for C < 0. As in the paper's comparison (Sec. 5.2.1) the PSF size is the CoC radius,
:math:`r = |C| / 2`, and scenes are rendered by depth layers (:mod:`.peer_layers`).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from dp5k_learn.batch import DPBatch

from .interface import DPSimulator
from .peer_layers import render_layered

SUPERSAMPLE = 8
"""Sub-samples per pixel side used to anti-alias the disk edge (like MATLAB's ``fspecial('disk')``)."""


@lru_cache(maxsize=512)
def _disk_left_psf_cached(coc_px: float) -> NDArray[np.float64]:
    r = abs(coc_px) / 2.0
    if r < 0.5:
        return np.full((1, 1), 0.5)
    R = int(math.ceil(r))
    k = 2 * R + 1
    s = SUPERSAMPLE
    sub = (np.arange(k * s) + 0.5) / s - (R + 0.5)  # sub-sample centres in px, pixel centres at integers
    ys, xs = np.meshgrid(sub, sub, indexing="ij")
    inside = xs**2 + ys**2 <= r * r
    sign = 1.0 if coc_px >= 0 else -1.0
    ramp = np.sqrt(np.clip(r * r - ys**2, 0.0, None)) - sign * xs
    w = np.where(inside, np.clip(ramp, 0.0, None), 0.0)
    h = w.reshape(k, s, k, s).sum(axis=(1, 3))
    return 0.5 * h / h.sum()


def translating_disk_psf(coc_px: float) -> NDArray[np.float64]:
    """Left-view translating-disk PSF for a signed CoC diameter ``coc_px``.

    Returns:
        (k, k) float64 with ``k = 2 ceil(|C|/2) + 1``, summing to 1/2; a 1x1 kernel of 0.5 when ``|C| < 1``.
        Convolution form: mass at negative x moves content left.
    """
    return _disk_left_psf_cached(float(coc_px)).copy()


class TranslatingDiskSimulator(DPSimulator):
    """Punnappurath et al.'s translating-disk PSF with the Butterworth simulator's layered blending."""

    name = "disk"

    def __init__(self, layer_step_px: float = 1.0) -> None:
        super().__init__()
        self.layer_step_px = layer_step_px

    def forward(self, batch: DPBatch):  # type: ignore[override]
        return render_layered(batch.sharp, batch.coc_px, batch.valid, translating_disk_psf, self.layer_step_px)
