r"""Butterworth-filter DP PSF (Abuolaim, Delbracio, Kelly, Brown, Milanfar, ICCV 2021).

Kernel of ``generate_bw_kernel.py``, for kernel radius :math:`R` (size :math:`k = 2R + 1`):

1. a filled circle of radius :math:`k // 2` (``cv2.circle``);
2. times the high-pass Butterworth response :math:`B(D) = D^{2n} / (1 + D^{2n})`,
   :math:`D = \rho / \rho_c`, cut-off :math:`\rho_c = (k - 1) / \text{cut\_off\_factor}`, rescaled to
   :math:`[\beta, 1]` (a ring: centre :math:`\beta`, rim 1);
3. padded by ``g // 2`` and Gaussian-blurred with :math:`g = \mathrm{round}(k \kappa) + 1` (made odd),
   :math:`\sigma = 0.3((g - 1)/2 - 1) + 0.8` (OpenCV's default for ``g``), :math:`\kappa = 1/7`;
4. times a linear 0 -> 1 ramp across the columns, normalised.

Published defaults: order :math:`n \in \{3, 6, 9\}`, cut-off factor :math:`\in \{2.5, 2\}`,
:math:`\beta \in \{0.1, 0.2\}` cycled per sequence; we use the first combination (3, 2.5, 0.1).
Their code applies the kernel with ``cv2.filter2D`` (correlation), so its +x ramp moves left-view content
to -x; here PSFs are in convolution form, so the left PSF for C > 0 is the horizontal mirror (ramp rising
toward -x), which is the same image. The right PSF is the horizontal flip (their ``np.flip`` is a 180 deg
rotation, equal to it because the kernel is vertically symmetric); C < 0 swaps the two. Their CoC is
rounded to integers and a CoC of 0 is set to 1; with the paper's "PSF size = CoC radius" the radius is
:math:`R = \max(1, \mathrm{round}(|C|/2))`, so even in-focus pixels get a 3 x 3 kernel, as in their code.
Each view's PSF sums to 1/2 here (their kernels sum to 1 each; dp5k views are on the scale where
left + right is the full-aperture image).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_learn.batch import DPBatch

from .interface import DPSimulator
from .peer_layers import render_layered


def butterworth_highpass(dist_px: NDArray[np.float64], cutoff_px: float, order: int) -> NDArray[np.float64]:
    r"""High-pass Butterworth response :math:`D^{2n} / (1 + D^{2n})`, :math:`D = \rho / \rho_c`; 1/2 at the cut-off."""
    d2n = (np.asarray(dist_px, dtype=np.float64) / cutoff_px) ** (2 * order)
    return d2n / (1.0 + d2n)


def butterworth_ring(radius_px: int, order: int = 3, cut_off_factor: float = 2.5, beta: float = 0.1) -> NDArray[np.float64]:
    """Steps 1-2: the disk times the Butterworth ring rescaled to [beta, 1], before smoothing. (k, k)."""
    k = 2 * radius_px + 1
    circle = cv2.circle(np.zeros((k, k), np.float64), (k // 2, k // 2), k // 2, 1.0, -1)
    yy, xx = np.mgrid[:k, :k] - k // 2
    b = butterworth_highpass(np.hypot(xx, yy), (k - 1) / cut_off_factor, order)
    b = (b - b.min()) / max(b.max() - b.min(), 1e-12) * (1.0 - beta) + beta
    return circle * b


@lru_cache(maxsize=512)
def _bw_left_psf_cached(coc_px: float, order: int, cut_off_factor: float, beta: float, smooth: float) -> NDArray[np.float64]:
    radius = max(1, int(round(abs(coc_px) / 2.0)))
    k = 2 * radius + 1
    ring = butterworth_ring(radius, order, cut_off_factor, beta)
    g = int(round(k * smooth)) + 1
    if g % 2 == 0:
        g += 1
    sigma = 0.3 * ((g - 1) * 0.5 - 1) + 0.8
    padded = np.pad(ring, g // 2)
    blurred = cv2.GaussianBlur(padded, (g, g), sigma, borderType=cv2.BORDER_CONSTANT) if g > 1 else padded
    n = blurred.shape[1]
    ramp_up = np.linspace(0.0, 1.0, n)[None, :]  # their k_l in correlation form: rises toward +x
    left_corr = blurred * ramp_up
    left_conv = left_corr[:, ::-1]  # convolution form: rises toward -x
    if coc_px < 0:
        left_conv = left_conv[:, ::-1]
    return 0.5 * left_conv / left_conv.sum()


@dataclass(frozen=True)
class ButterworthParams:
    """Abuolaim et al.'s kernel constants (first combination of their published grid)."""

    order: int = 3
    cut_off_factor: float = 2.5
    beta: float = 0.1
    smooth: float = 1.0 / 7.0


def butterworth_psf(coc_px: float, params: ButterworthParams = ButterworthParams()) -> NDArray[np.float64]:
    """Left-view Butterworth DP PSF for a signed CoC diameter (convolution form, sum 1/2)."""
    return _bw_left_psf_cached(float(coc_px), params.order, params.cut_off_factor, params.beta, params.smooth).copy()


class ButterworthSimulator(DPSimulator):
    """Abuolaim et al.'s Butterworth PSF with depth-layer blending (coverage normalised)."""

    name = "butterworth"

    def __init__(self, params: ButterworthParams | None = None, layer_step_px: float = 1.0) -> None:
        super().__init__()
        self.params = params or ButterworthParams()
        self.layer_step_px = layer_step_px

    def forward(self, batch: DPBatch):  # type: ignore[override]
        return render_layered(
            batch.sharp, batch.coc_px, batch.valid, lambda c: butterworth_psf(c, self.params), self.layer_step_px
        )
