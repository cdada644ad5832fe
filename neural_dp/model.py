r"""The Neural DP Simulator network (Sec. 4.1): a U-Net kernel-prediction network.

Inputs (5 channels): the sharp image (3), the signed CoC map scaled by ``1 / coc_scale_px`` (1) and depth
min-max normalised to [0, 1] per image with invalid pixels set to -1 (1). Outputs per pixel: a K x K
softmax kernel for the left view (K = 5; one kernel shared by the colour channels as in the paper, or one
per channel with ``kernel_per_channel``) and two 3-channel residual images. The right kernel is the
**horizontal** flip of the left one (Eq. 2, :func:`neural_dp.kernels.flip_lr`):

.. math::
    \check I_l = g_l \odot (W_l \circledast I_s) + A_l, \qquad
    \check I_r = g_r \odot (\mathrm{hflip}(W_l) \circledast I_s) + A_r

:math:`g_l, g_r` are per-channel view gains (3 numbers each; Eq. 2's 1/2, initialised from the training
data's view/sharp brightness ratio) so that a per-view scale, which an additive residual represents badly,
costs nothing to learn.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .kernels import apply_kernels, flip_lr


@dataclass(frozen=True)
class ModelConfig:
    """Network hyper-parameters."""

    base_channels: int = 64
    """Channels of the first U-Net level (doubles per level; the paper's U-Net is 64..1024)."""
    levels: int = 4
    """Number of down-sampling steps."""
    kernel_size: int = 5
    """Side of the predicted per-pixel kernels (the paper: 5)."""
    kernel_per_channel: bool = False
    """One kernel per colour channel (False: one shared kernel, as in the paper and its code)."""
    norm: str = "batch"
    """Normalisation in the conv blocks: "batch" (the released code), "group" or "none"."""
    dropout: float = 0.0
    """Dropout probability at the bottleneck."""
    coc_scale_px: float = 10.0
    """The CoC input channel is ``coc_px / coc_scale_px``."""
    tile_px: int = 512
    """Inference tile side (bounds memory at full resolution); 0 disables tiling."""
    tile_margin_px: int = 96
    """Context added around each inference tile and discarded after (>= the U-Net's reach, about 94 px at
    4 levels, makes tiled output equal the whole-image output)."""


def _norm(kind: str, ch: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(ch)
    if kind == "group":
        return nn.GroupNorm(min(8, ch), ch)
    return nn.Identity()


class _Block(nn.Sequential):
    def __init__(self, cin: int, cout: int, norm: str) -> None:
        super().__init__(
            nn.Conv2d(cin, cout, 3, padding=1, bias=norm == "none"), _norm(norm, cout), nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1, bias=norm == "none"), _norm(norm, cout), nn.ReLU(inplace=True),
        )


class UNetKPN(nn.Module):
    """U-Net predicting per-pixel left kernels (softmax) and two residual images.

    Args:
        cfg: the :class:`ModelConfig`.

    Shape:
        ``predict(x)`` with x (B, 5, H, W), H and W multiples of ``2 ** levels``, returns
        ``(weights, res_l, res_r)``: weights (B, K*K, H, W) or (B, 3, K*K, H, W), residuals (B, 3, H, W).
        ``forward(sharp, inputs)`` with sharp (B, 3, H, W) and inputs (B, 5, H, W) of any size returns the
        two views ``(left, right)``, each (B, 3, H, W) (everything inside ``forward``, so DDP sees it all).
    """

    in_channels = 5

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        ch = [cfg.base_channels * 2**i for i in range(cfg.levels + 1)]
        self.enc = nn.ModuleList([_Block(self.in_channels, ch[0], cfg.norm)])
        self.enc.extend(_Block(ch[i], ch[i + 1], cfg.norm) for i in range(cfg.levels))
        self.drop = nn.Dropout2d(cfg.dropout) if cfg.dropout > 0 else nn.Identity()
        self.dec = nn.ModuleList(_Block(ch[i + 1] + ch[i], ch[i], cfg.norm) for i in reversed(range(cfg.levels)))
        k2 = cfg.kernel_size**2
        self.n_kernel = k2 * (3 if cfg.kernel_per_channel else 1)
        self.head = nn.Conv2d(ch[0], self.n_kernel + 6, 1)
        # Start as the identity: zero weights, kernel logits peaked on the centre tap, zero residuals.
        nn.init.zeros_(self.head.weight)
        bias = torch.zeros(self.n_kernel + 6)
        centre = bias[: self.n_kernel].view(-1, k2)
        centre[:, k2 // 2] = 4.0
        with torch.no_grad():
            self.head.bias.copy_(bias)
        self.view_gain = nn.Parameter(torch.full((2, 3), 0.5))

    @property
    def multiple(self) -> int:
        return 2**self.cfg.levels

    def predict(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The per-pixel left kernels (softmax) and the two residual images (see class docstring)."""
        skips = []
        h = x
        for i, block in enumerate(self.enc):
            h = block(h if i == 0 else F.max_pool2d(h, 2))
            skips.append(h)
        h = self.drop(skips.pop())
        for block in self.dec:
            skip = skips.pop()
            h = F.interpolate(h, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            h = block(torch.cat([h, skip], dim=1))
        out = self.head(h)
        B, _, H, W = out.shape
        k2 = self.cfg.kernel_size**2
        logits = out[:, : self.n_kernel]
        if self.cfg.kernel_per_channel:
            weights = torch.softmax(logits.view(B, 3, k2, H, W), dim=2)
        else:
            weights = torch.softmax(logits, dim=1)
        return weights, out[:, self.n_kernel : self.n_kernel + 3], out[:, self.n_kernel + 3 :]

    def forward(self, sharp: Tensor, inputs: Tensor) -> tuple[Tensor, Tensor]:
        """Both DP views from the sharp image and the network input (pads to a multiple of ``2 ** levels``)."""
        H, W = sharp.shape[-2:]
        m = self.multiple
        ph, pw = (-H) % m, (-W) % m
        x = F.pad(inputs, (0, pw, 0, ph), mode="replicate") if (ph or pw) else inputs
        weights, res_l, res_r = self.predict(x)
        weights = weights[..., :H, :W]
        gain_l = self.view_gain[0].view(1, 3, 1, 1)
        gain_r = self.view_gain[1].view(1, 3, 1, 1)
        left = gain_l * apply_kernels(sharp, weights) + res_l[..., :H, :W]
        right = gain_r * apply_kernels(sharp, flip_lr(weights)) + res_r[..., :H, :W]
        return left, right


def normalize_depth(depth_mm: Tensor, valid: Tensor) -> Tensor:
    """Per image, min-max scale valid depth to [0, 1]; invalid pixels -1 (the paper's depth input).

    Args:
        depth_mm: (B, 1, H, W). valid: (B, 1, H, W) bool.

    Returns:
        (B, 1, H, W).
    """
    big = torch.finfo(depth_mm.dtype).max
    lo = torch.where(valid, depth_mm, torch.full_like(depth_mm, big)).amin(dim=(1, 2, 3), keepdim=True)
    hi = torch.where(valid, depth_mm, torch.full_like(depth_mm, -big)).amax(dim=(1, 2, 3), keepdim=True)
    span = (hi - lo).clamp_min(1e-6)
    norm = ((depth_mm - lo) / span).clamp(0, 1)
    return torch.where(valid, norm, torch.full_like(depth_mm, -1.0))
