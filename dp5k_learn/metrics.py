r"""Masked image metrics of Table 2: MAE, PSNR and SSIM with invalid-depth pixels left out.

Definitions (pinned by ``tests/learn/test_metrics.py``):

* **MAE** over valid pixels and channels: :math:`\sum_m |p - g| / (C \sum m)`.
* **PSNR** per image from the MSE over valid pixels and channels, data range 1.0:
  :math:`10 \log_{10}(1 / MSE)`.
* **SSIM** (Wang et al. 2004): Gaussian window 11 x 11, sigma 1.5, K1 = 0.01, K2 = 0.03, data range 1.0,
  population (not sample) statistics. The SSIM *map* is evaluated only where the whole window fits in the
  image ("valid" convolution, like scikit-image with ``gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False``), and the mask is eroded by the window radius (5 px) so no window that
  touches an invalid pixel counts. On an all-ones mask this equals scikit-image's
  ``structural_similarity(..., gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
  data_range=1, channel_axis=-1)``.

Every function takes ``(B, C, H, W)`` predictions and targets and a ``(B, 1, H, W)`` mask (bool or 0/1)
and returns a ``(B,)`` tensor, one value per image; average over images yourself (what the paper's
tables report). Images with no valid pixel give NaN.
"""

from __future__ import annotations


import torch
import torch.nn.functional as F
from torch import Tensor

from dp5k_common.errors import BadInputError

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


def _check(pred: Tensor, target: Tensor, mask: Tensor, where: str) -> Tensor:
    if pred.shape != target.shape or pred.ndim != 4:
        raise BadInputError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} must be equal (B,C,H,W)", where=where)
    if mask.ndim != 4 or mask.shape[1] != 1 or mask.shape[0] != pred.shape[0] or mask.shape[-2:] != pred.shape[-2:]:
        raise BadInputError(f"mask {tuple(mask.shape)} must be (B,1,H,W) matching {tuple(pred.shape)}", where=where)
    return mask.to(pred.dtype)


def masked_mae(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Mean absolute error over valid pixels and channels, per image. Returns (B,)."""
    m = _check(pred, target, mask, "masked_mae")
    C = pred.shape[1]
    return ((pred - target).abs() * m).sum((1, 2, 3)) / (C * m.sum((1, 2, 3)))


def masked_psnr(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0) -> Tensor:
    """PSNR in dB from the MSE over valid pixels and channels, per image. Returns (B,)."""
    m = _check(pred, target, mask, "masked_psnr")
    C = pred.shape[1]
    mse = ((pred - target) ** 2 * m).sum((1, 2, 3)) / (C * m.sum((1, 2, 3)))
    return 10.0 * torch.log10(data_range**2 / mse.clamp_min(1e-20))


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, *, dtype: torch.dtype = torch.float32,
                    device: torch.device | str = "cpu") -> Tensor:
    """Normalised 1-D Gaussian of ``size`` taps (odd), standard deviation ``sigma`` px. Returns (size,)."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim_map(pred: Tensor, target: Tensor, data_range: float = 1.0, window: int = SSIM_WINDOW,
             sigma: float = SSIM_SIGMA) -> Tensor:
    r"""The SSIM map on the "valid" region (windows fully inside the image).

    .. math::
        SSIM = \frac{(2\mu_p\mu_g + c_1)(2\sigma_{pg} + c_2)}{(\mu_p^2+\mu_g^2+c_1)(\sigma_p^2+\sigma_g^2+c_2)},
        \quad c_1 = (0.01 L)^2,\ c_2 = (0.03 L)^2

    Args:
        pred, target: (B, C, H, W).

    Returns:
        (B, C, H - window + 1, W - window + 1).
    """
    C = pred.shape[1]
    g = gaussian_window(window, sigma, dtype=pred.dtype, device=pred.device)
    gx = g.view(1, 1, 1, -1).expand(C, 1, 1, window)
    gy = g.view(1, 1, -1, 1).expand(C, 1, window, 1)

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(t, gx, groups=C), gy, groups=C)

    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    mu_p, mu_g = blur(pred), blur(target)
    s_pp = blur(pred * pred) - mu_p**2
    s_gg = blur(target * target) - mu_g**2
    s_pg = blur(pred * target) - mu_p * mu_g
    num = (2 * mu_p * mu_g + c1) * (2 * s_pg + c2)
    den = (mu_p**2 + mu_g**2 + c1) * (s_pp + s_gg + c2)
    return num / den


def masked_ssim(pred: Tensor, target: Tensor, mask: Tensor, data_range: float = 1.0, window: int = SSIM_WINDOW,
                sigma: float = SSIM_SIGMA) -> Tensor:
    """Mean SSIM over the windows that lie fully on valid pixels, per image (see module docstring).

    Args:
        pred, target: (B, C, H, W), H and W at least ``window``.
        mask: (B, 1, H, W) bool or 0/1.

    Returns:
        (B,) mean SSIM; NaN for an image with no fully valid window.
    """
    m = _check(pred, target, mask, "masked_ssim")
    if min(pred.shape[-2:]) < window:
        raise BadInputError(f"images {tuple(pred.shape[-2:])} are smaller than the SSIM window {window}", where="masked_ssim")
    smap = ssim_map(pred, target, data_range, window, sigma)
    # A window centred at (y, x) is fully valid iff min(mask) over it is 1: erode by the window radius.
    eroded = -F.max_pool2d(-m, window, stride=1)
    C = pred.shape[1]
    return (smap * eroded).sum((1, 2, 3)) / (C * eroded.sum((1, 2, 3)))


def view_metrics(pred_l: Tensor, pred_r: Tensor, gt_l: Tensor, gt_r: Tensor, mask: Tensor) -> dict[str, Tensor]:
    """Table 2's three metrics per image, each the mean over the left and right views.

    Returns:
        ``{"mae": (B,), "psnr": (B,), "ssim": (B,)}``.
    """
    out = {}
    for name, fn in (("mae", masked_mae), ("psnr", masked_psnr), ("ssim", masked_ssim)):
        out[name] = 0.5 * (fn(pred_l, gt_l, mask) + fn(pred_r, gt_r, mask))
    return out
