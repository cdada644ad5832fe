"""The DP deblurring network: a DPDNet-like U-Net from the two DP views (6 channels) to the sharp image (3 channels).

DPDNet (Abuolaim & Brown 2020) is an encoder-decoder with skip connections that takes the left and right DP views
stacked as six channels and predicts the all-in-focus image. This one keeps that shape at a configurable size:
``levels`` encoder stages of two 3 x 3 convolutions + ReLU, channel width doubling per stage from
``base_channels`` (DPDNet: 4 stages, 64), 2 x 2 max-pooling down, bilinear upsampling + 3 x 3 convolution up,
concatenated skips. With ``input_skip`` the network predicts a correction of the blurred input: output =
(L + R) + U(L, R), which lets a small network trained for a few hundred steps start from the blurred image
instead of from black (DPDNet has no such skip; set it False for the published form).

All images are linear intensities, (B, C, H, W), on the dataset's scale; any H, W (inputs are padded by
replication to a multiple of ``2 ** levels`` and the output cropped back).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

DP_CHANNELS = 6
"""Left view RGB then right view RGB."""
SHARP_CHANNELS = 3
HEAD_INIT_SCALE = 0.1
"""With ``input_skip``, the output layer's default initial weights are scaled by this: the correction starts small
(the prediction near L + R) but not zero, so from the first step the gradient reaches every layer (a zero head would
pass none back, and the U-Net would learn only its last layer for the first hundred steps)."""


@dataclass(frozen=True)
class DeblurNetConfig:
    """Size of the U-Net (DPDNet: ``levels=4, base_channels=64, input_skip=False``)."""

    base_channels: int = 16
    levels: int = 3
    input_skip: bool = True
    """Predict a correction of the blurred input (L + R) instead of the image itself."""


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.ReLU(inplace=True))


class DPDeblurNet(nn.Module):
    """U-Net ``(left, right) -> sharp``; see the module docstring."""

    def __init__(self, cfg: DeblurNetConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or DeblurNetConfig()
        widths = [self.cfg.base_channels * 2**i for i in range(self.cfg.levels + 1)]
        self.down = nn.ModuleList([_block(DP_CHANNELS if i == 0 else widths[i - 1], widths[i]) for i in range(self.cfg.levels)])
        self.bottom = _block(widths[self.cfg.levels - 1], widths[self.cfg.levels])
        self.up_conv = nn.ModuleList([nn.Conv2d(widths[i + 1], widths[i], 3, padding=1) for i in range(self.cfg.levels)])
        self.up = nn.ModuleList([_block(2 * widths[i], widths[i]) for i in range(self.cfg.levels)])
        self.head = nn.Conv2d(widths[0], SHARP_CHANNELS, 1)
        if self.cfg.input_skip:  # start near the identity on the blurred input, with gradients reaching every layer
            with torch.no_grad():
                self.head.weight.mul_(HEAD_INIT_SCALE)
                self.head.bias.zero_()

    def forward(self, left: Tensor, right: Tensor) -> Tensor:
        """(B, 3, H, W) left and right views -> (B, 3, H, W) predicted sharp image."""
        H, W = left.shape[-2:]
        m = 2**self.cfg.levels
        pad = (0, (-W) % m, 0, (-H) % m)
        x = F.pad(torch.cat([left, right], 1), pad, mode="replicate")
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = self.bottom(x)
        for i in reversed(range(self.cfg.levels)):
            x = F.interpolate(x, size=skips[i].shape[-2:], mode="bilinear", align_corners=False)
            x = self.up[i](torch.cat([F.relu(self.up_conv[i](x)), skips[i]], 1))
        out = self.head(x)[..., :H, :W]
        return out + left + right if self.cfg.input_skip else out
