r"""The masked edge-aware Charbonnier loss of Eq. (8) / (9).

.. math::
    \rho(d) = \sqrt{d^2 + \epsilon^2}, \quad \epsilon = 10^{-3}

    D(p, g, M) = \frac{\sum M\, \rho(p - g)}{C \sum M}

    D_\nabla(p, g, M) = \frac{\sum M_x \rho(\partial_x p - \partial_x g) + \sum M_y \rho(\partial_y p - \partial_y g)}
                             {C (\sum M_x + \sum M_y)}

    loss = D(\check I_l, \hat I_l) + D_\nabla(\check I_l, \hat I_l) + D(\check I_r, \hat I_r) + D_\nabla(\check I_r, \hat I_r)

Eq. (9) writes the mask inside the square root, :math:`\sqrt{M d^2 + \epsilon^2}`; that differs from the
form above only by the constant :math:`\epsilon \cdot \#invalid / \sum M`, so the gradients are identical and
the value is a true mean over valid pixels. A finite difference counts only where **both** of its pixels
are valid (:math:`M_x = M(x) M(x+1)`), so the mask edge is never penalised.
"""

from __future__ import annotations

import torch
from torch import Tensor

CHARBONNIER_EPS = 1e-3


def charbonnier(d: Tensor, eps: float = CHARBONNIER_EPS) -> Tensor:
    r"""Elementwise :math:`\sqrt{d^2 + \epsilon^2}` (MPRNet's form, eps squared inside the root)."""
    return torch.sqrt(d * d + eps * eps)


def masked_charbonnier(pred: Tensor, target: Tensor, mask: Tensor, eps: float = CHARBONNIER_EPS) -> Tensor:
    """Mean Charbonnier penalty over valid pixels and channels of the whole batch (a scalar).

    Args:
        pred, target: (B, C, H, W).
        mask: (B, 1, H, W) bool or 0/1.
    """
    m = mask.to(pred.dtype)
    C = pred.shape[1]
    return (charbonnier(pred - target, eps) * m).sum() / (C * m.sum()).clamp_min(1.0)


def masked_gradient_charbonnier(pred: Tensor, target: Tensor, mask: Tensor, eps: float = CHARBONNIER_EPS) -> Tensor:
    """Charbonnier penalty on horizontal and vertical finite differences, both pixels valid (a scalar)."""
    m = mask.to(pred.dtype)
    C = pred.shape[1]
    d = pred - target
    dx = d[..., :, 1:] - d[..., :, :-1]
    dy = d[..., 1:, :] - d[..., :-1, :]
    mx = m[..., :, 1:] * m[..., :, :-1]
    my = m[..., 1:, :] * m[..., :-1, :]
    num = (charbonnier(dx, eps) * mx).sum() + (charbonnier(dy, eps) * my).sum()
    return num / (C * (mx.sum() + my.sum())).clamp_min(1.0)


def dp_loss(pred_l: Tensor, pred_r: Tensor, gt_l: Tensor, gt_r: Tensor, mask: Tensor,
            grad_weight: float = 1.0, eps: float = CHARBONNIER_EPS) -> Tensor:
    """Eq. (8): image plus gradient Charbonnier terms on both views (a scalar)."""
    total = masked_charbonnier(pred_l, gt_l, mask, eps) + masked_charbonnier(pred_r, gt_r, mask, eps)
    if grad_weight:
        total = total + grad_weight * (
            masked_gradient_charbonnier(pred_l, gt_l, mask, eps) + masked_gradient_charbonnier(pred_r, gt_r, mask, eps)
        )
    return total
