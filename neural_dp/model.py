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

**Multi-scale kernels** (``ModelConfig.multiscale_levels = n > 0``; off by default, which is the paper's
model and loads every existing checkpoint unchanged). A K x K kernel reaches only K // 2 px (2 px for K = 5),
so a blur disc of 10 px must be faked by the residuals. With n levels the network also predicts, per pixel,
a kernel :math:`W^{(s)}` and a blend weight :math:`a_s` for each scale ``s = 1..n`` with dilation
:math:`d_s = 2^s`. Kernel ``s`` is applied with its taps ``d_s`` px apart to the sharp image pre-filtered by
a centred box of width ``d_s`` (:func:`box_prefilter`), so its K x K taps tile a ``K d_s``-px square without
gaps (a piecewise-constant kernel of reach about ``(K // 2) d_s + d_s / 2`` px: 10 px at K = 5, d = 4):

.. math::
    B_l = W_l \circledast I_s + \sum_s a_s \left(W^{(s)}_l \circledast_{d_s} P_{d_s} I_s - W_l \circledast I_s\right),
    \qquad a_s = \tanh(z_s)

and the same with every kernel mirrored for the right view (the blend weights are shared: mirroring
does not change them). The blend is affine (its weights sum to 1), so flat regions keep their brightness.
With :math:`z_s = 0` the output is exactly the single-scale model's; :func:`extend_multiscale` uses that to
turn a trained single-scale network into a multi-scale one with the same output, to be fine-tuned.

**Physics first** (``ModelConfig.prior = "physical"``; what ``dp5k train`` builds by default, see
:mod:`neural_dp.train`). The network starts from a physical simulator's views :math:`P_l, P_r` (the base model
fitted on the train pairs, or a diagnosed model; :class:`~neural_dp.simulators.neural.NeuralDPSimulator` renders
them) and learns only what that model gets wrong: what the lens does differently (a per-pixel affine K x K
correction kernel applied to the physical views, and two residual images), then what the sensor does (per
photodiode a gain and a crosstalk, quadratic in the field position, :meth:`UNetKPN.sensor`),

.. math::
    O_l = P_l + \sum_t k^l_t \,(S_t P_l - P_l) + A_l, \qquad
    \check I_l = g_L \odot \big((1 - c_L)\, O_l + c_L\, O_r\big)

(:math:`S_t` shifts by tap ``t``; the kernel's weights are free, so a correction can sharpen, blur or shift, and
its taps always sum to "keep the brightness"). Every head weight and bias and every sensor coefficient starts at
exactly 0, so **at initialisation the output equals the physical model's bit for bit**
(``tests/neural_dp/test_physics_first.py``). The correction respects the two symmetries of DP image formation
(Eq. 2): the right kernel is the mirror of the left, ``k^r = hflip(k^l)``, and the **sign of the CoC** swaps the
views (a point in front of focus sends to the left view what a point behind focus sends to the right one): the
network sees the physical views ordered as (a, b) = (L, R) behind focus and (R, L) in front of it, with
:math:`|C|` instead of :math:`C`, and its kernel and residuals for view a go to L behind focus and to R in front
(``k^l = s\, k + (1 - s)\, hflip(k)``, :math:`s = (1 + \tanh(C / 0.5\,px)) / 2`, continuous through focus).
The sensor stage does not turn with the sign: gains and crosstalk belong to the photodiodes (without it, an L/R
imbalance learned behind focus came out on the wrong view in front of focus).
What it learns behind focus therefore applies, mirrored, in front of it: on the Sdirt photos (train behind focus,
test in front) the network without this structure gained on held-out tiles of its own photo and lost 2.5 dB on
the other photo. Inputs (13 channels): sharp, :math:`P_a, P_b`, :math:`|C| / 10` px, the valid-depth mask and the
pixel's field position (x, y) in its camera frame (tiles know where they were cut). Depth is not an input: a
planar target's min-max normalised depth is meaningless, and the CoC carries what the blur needs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dp5k_common.errors import BadInputError

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
    multiscale_levels: int = 0
    """Extra kernel scales at dilations 2, 4, ..., 2**n px blended per pixel (0 = off: the paper's model).
    See the module docstring; the reach of the kernels grows from K // 2 to about (K // 2 + 1/2) 2**n px."""
    tile_px: int = 512
    """Inference tile side (bounds memory at full resolution); 0 disables tiling."""
    tile_margin_px: int = 0
    """Context (px) added around each inference tile and discarded after. At least the network's receptive
    radius (:attr:`UNetKPN.receptive_radius_px`: 122 px at 4 levels) is always used, rounded up to a multiple
    of ``2 ** levels``, so the tiled output equals the whole-image output; 0 = exactly that."""
    prior: str = "none"
    """What the network starts from: ``"none"``, the paper's network (its kernels act on the sharp image; what a
    checkpoint without this key is), or ``"physical"``, a correction of a physical simulator's views that is
    exactly that simulator at initialisation (the module docstring; ``dp5k train``'s default)."""
    prior_spec: str = ""
    """The physical simulator of ``prior = "physical"`` as JSON (:func:`neural_dp.simulators.base.spec.model_to_spec`:
    the base model with its fitted parameters and any diagnosed effects); ``dp5k train`` fills it in (leave it
    empty; empty = the base model at its defaults)."""


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
        With ``multiscale_levels = n > 0``, ``predict_scales(x)`` returns the n extra scales' kernels (each
        shaped like ``weights``) and the blend weights (B, n, H, W) in (-1, 1) (see the module docstring).
    """

    in_channels = 5
    """Trunk inputs of the paper's network (``prior = "none"``); 13 with a physical prior."""
    physical_inputs = 11
    """Channels of ``inputs`` with a physical prior: P_l (3), P_r (3), signed CoC px (1), valid (1), field x, y (2),
    mirrored (1) (:func:`neural_dp.simulators.neural.model_inputs`)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        if cfg.prior not in PRIORS:
            raise BadInputError(f"model.prior must be one of {', '.join(PRIORS)}, got {cfg.prior!r}", where="ModelConfig")
        self.cfg = cfg
        self.physical = cfg.prior == "physical"
        if self.physical:
            self.in_channels = 13
        ch = [cfg.base_channels * 2**i for i in range(cfg.levels + 1)]
        self.enc = nn.ModuleList([_Block(self.in_channels, ch[0], cfg.norm)])
        self.enc.extend(_Block(ch[i], ch[i + 1], cfg.norm) for i in range(cfg.levels))
        self.drop = nn.Dropout2d(cfg.dropout) if cfg.dropout > 0 else nn.Identity()
        self.dec = nn.ModuleList(_Block(ch[i + 1] + ch[i], ch[i], cfg.norm) for i in reversed(range(cfg.levels)))
        k2 = cfg.kernel_size**2
        self.n_kernel = k2 * (3 if cfg.kernel_per_channel else 1)
        self.head = nn.Conv2d(ch[0], self.n_kernel + 6, 1)
        # Start as the identity: zero weights, kernel logits peaked on the centre tap (the paper's network) or a
        # zero correction (physical prior: the output is then exactly the physical views), zero residuals.
        nn.init.zeros_(self.head.weight)
        bias = torch.zeros(self.n_kernel + 6)
        if not self.physical:
            centre = bias[: self.n_kernel].view(-1, k2)
            centre[:, k2 // 2] = 4.0
        with torch.no_grad():
            self.head.bias.copy_(bias)
        self.view_gain = nn.Parameter(torch.full((2, 3), 0.5))
        if self.physical:  # the sensor stage instead of constant gains: per photodiode, functions of the field
            del self.view_gain
            self.sensor_gain = nn.Parameter(torch.zeros(2, 3, len(FIELD_TERMS)))
            self.sensor_xtalk = nn.Parameter(torch.zeros(2, len(FIELD_TERMS)))
        self.n_scales = int(cfg.multiscale_levels)
        if self.n_scales < 0:
            raise BadInputError(f"multiscale_levels must be >= 0, got {cfg.multiscale_levels}", where="ModelConfig")
        self.scale_head: nn.Conv2d | None = None
        if self.n_scales:
            # Per extra scale: n_kernel kernel logits, then one blend logit per scale at the end.
            self.scale_head = nn.Conv2d(ch[0], self.n_scales * (self.n_kernel + 1), 1)
            nn.init.zeros_(self.scale_head.weight)
            sb = torch.zeros(self.n_scales * (self.n_kernel + 1))
            if not self.physical:  # a physical prior's extra scales are corrections too: zero
                sb[: self.n_scales * self.n_kernel].view(-1, k2)[:, k2 // 2] = 4.0
            with torch.no_grad():
                self.scale_head.bias.copy_(sb)  # blend logits 0: exactly the single-scale output

    @property
    def multiple(self) -> int:
        return 2**self.cfg.levels

    @property
    def dilations(self) -> tuple[int, ...]:
        """Tap spacing in px of each extra scale: (2, 4, ..., 2**n); empty when multi-scale is off."""
        return tuple(2**s for s in range(1, self.n_scales + 1))

    @property
    def reach_px(self) -> int:
        """How far (px) the kernels read from a pixel: K // 2, or (K // 2) d + d // 2 at the largest dilation d."""
        r = self.cfg.kernel_size // 2
        d = max(self.dilations, default=1)
        return r * d + (d // 2 if d > 1 else 0)

    @property
    def receptive_radius_px(self) -> int:
        """How far (px, along either axis) from an output pixel the input can change its value.

        The larger of the kernels' reach on the sharp image (:attr:`reach_px`) and the U-Net trunk's worst-case
        receptive-field radius. Encoder level k (pixels of ``2**k`` px) widens a pixel's footprint by ``a_k``:
        ``a_0 = 2`` (two 3 x 3 convs), ``a_{k+1} = a_k + 2 * 2**(k+1)`` (2 x 2 max-pool, two convs). Decoder
        level k reads the bilinear upsampling of level k + 1 (coarse neighbours up to ``2**(k+1)`` px beyond a
        pixel's footprint) beside the skip: ``d_k = max(d_{k+1} + 2**(k+1), a_k) + 2 * 2**k`` from
        ``d_levels = a_levels``. 26 px at 2 levels, 58 at 3, 122 at 4.
        """
        a = [2]
        for k in range(1, self.cfg.levels + 1):
            a.append(a[-1] + 2 * 2**k)
        d = a[-1]
        for k in reversed(range(self.cfg.levels)):
            d = max(d + 2 ** (k + 1), a[k]) + 2 * 2**k
        return max(d, self.reach_px)

    def _trunk(self, x: Tensor) -> Tensor:
        """U-Net features at full resolution, (B, base_channels, H, W)."""
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
        return h

    def _kernels(self, logits: Tensor) -> Tensor:
        """Softmax kernels from (B, n_kernel, H, W) logits: (B, K*K, H, W) or (B, 3, K*K, H, W); with a physical
        prior the free correction weights themselves (no softmax: a correction's taps need not be positive)."""
        B, _, H, W = logits.shape
        if self.cfg.kernel_per_channel:
            w = logits.view(B, 3, self.cfg.kernel_size**2, H, W)
            return w if self.physical else torch.softmax(w, dim=2)
        return logits if self.physical else torch.softmax(logits, dim=1)

    def _heads(self, h: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        out = self.head(h)
        weights = self._kernels(out[:, : self.n_kernel])
        return weights, out[:, self.n_kernel : self.n_kernel + 3], out[:, self.n_kernel + 3 :]

    def _scale_heads(self, h: Tensor) -> tuple[list[Tensor], Tensor]:
        """Per extra scale its kernels (as :meth:`_kernels`), and the blend weights (B, n_scales, H, W) in (-1, 1)."""
        if self.scale_head is None:
            raise BadInputError("multi-scale kernels are off (ModelConfig.multiscale_levels = 0)", where="UNetKPN")
        out = self.scale_head(h)
        nk = self.n_kernel
        kernels = [self._kernels(out[:, s * nk : (s + 1) * nk]) for s in range(self.n_scales)]
        return kernels, torch.tanh(out[:, self.n_scales * nk :])

    def predict(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The per-pixel left kernels (softmax) and the two residual images (see class docstring)."""
        return self._heads(self._trunk(x))

    def predict_scales(self, x: Tensor) -> tuple[list[Tensor], Tensor]:
        """The extra scales' left kernels (one tensor per scale, shaped like ``predict``'s weights) and blend
        weights (B, n_scales, H, W); requires ``multiscale_levels > 0``."""
        return self._scale_heads(self._trunk(x))

    @torch.no_grad()
    def init_scales_from_base(self) -> None:
        """Make every extra scale's kernel head a copy of the base kernel head and zero the blend head.

        Afterwards the network's output equals the single-scale output exactly (blend weights are
        ``tanh(0) = 0``), and each extra scale starts as the learned kernel stretched by its dilation.
        """
        if self.scale_head is None:
            return
        if self.physical:  # corrections: zero is exactly the single-scale output
            self.scale_head.weight.zero_()
            self.scale_head.bias.zero_()
            return
        nk = self.n_kernel
        for s in range(self.n_scales):
            self.scale_head.weight[s * nk : (s + 1) * nk] = self.head.weight[:nk]
            self.scale_head.bias[s * nk : (s + 1) * nk] = self.head.bias[:nk]
        self.scale_head.weight[self.n_scales * nk :] = 0.0
        self.scale_head.bias[self.n_scales * nk :] = 0.0

    def forward(self, sharp: Tensor, inputs: Tensor) -> tuple[Tensor, Tensor]:
        """Both DP views from the sharp image and the network input (pads to a multiple of ``2 ** levels``)."""
        if self.physical:
            return self._forward_physical(sharp, inputs)
        H, W = sharp.shape[-2:]
        m = self.multiple
        ph, pw = (-H) % m, (-W) % m
        x = F.pad(inputs, (0, pw, 0, ph), mode="replicate") if (ph or pw) else inputs
        h = self._trunk(x)
        weights, res_l, res_r = self._heads(h)
        weights = weights[..., :H, :W]
        blur_l = apply_kernels(sharp, weights)
        blur_r = apply_kernels(sharp, flip_lr(weights))
        if self.scale_head is not None:
            kernels, blend = self._scale_heads(h)
            base_l, base_r = blur_l, blur_r
            for s, d in enumerate(self.dilations):
                ws = kernels[s][..., :H, :W]
                a = blend[:, s : s + 1, :H, :W]
                pre = box_prefilter(sharp, d)
                blur_l = blur_l + a * (apply_kernels(pre, ws, dilation=d) - base_l)
                blur_r = blur_r + a * (apply_kernels(pre, flip_lr(ws), dilation=d) - base_r)
        gain_l = self.view_gain[0].view(1, 3, 1, 1)
        gain_r = self.view_gain[1].view(1, 3, 1, 1)
        left = gain_l * blur_l + res_l[..., :H, :W]
        right = gain_r * blur_r + res_r[..., :H, :W]
        return left, right

    def _forward_physical(self, sharp: Tensor, inputs: Tensor) -> tuple[Tensor, Tensor]:
        """The physical views corrected (module docstring); ``inputs`` as :attr:`physical_inputs`."""
        if inputs.shape[1] != self.physical_inputs:
            raise BadInputError(f"a physical-prior network takes {self.physical_inputs} input channels, got "
                                f"{inputs.shape[1]}", where="UNetKPN")
        H, W = sharp.shape[-2:]
        pl, pr, coc, valid = inputs[:, 0:3], inputs[:, 3:6], inputs[:, 6:7], inputs[:, 7:8]
        field, mirrored = inputs[:, 8:10], inputs[:, 10:11]
        s = sign_weight(coc)
        pa, pb = s * pl + (1 - s) * pr, s * pr + (1 - s) * pl
        x = torch.cat([sharp, pa, pb, coc.abs() / self.cfg.coc_scale_px, valid, field], dim=1)
        m = self.multiple
        ph, pw = (-H) % m, (-W) % m
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        h = self._trunk(x)
        k, ra, rb = self._heads(h)
        k, ra, rb = k[..., :H, :W], ra[..., :H, :W], rb[..., :H, :W]
        k_l = mirror_by_sign(k, s)
        corr_l, corr_r = pl + correction(pl, k_l), pr + correction(pr, flip_lr(k_l))
        if self.scale_head is not None:
            kernels, _ = self._scale_heads(h)  # a physical prior's extra scales are added corrections (no blend)
            for ks, d in zip(kernels, self.dilations):
                ks_l = mirror_by_sign(ks[..., :H, :W], s)
                corr_l = corr_l + correction(box_prefilter(pl, d), ks_l, d)
                corr_r = corr_r + correction(box_prefilter(pr, d), flip_lr(ks_l), d)
        res_l, res_r = s * ra + (1 - s) * rb, s * rb + (1 - s) * ra  # light the kernels cannot reach: optics too
        return self.sensor(corr_l + res_l, corr_r + res_r, field, mirrored > 0.5)

    def sensor(self, left: Tensor, right: Tensor, field: Tensor, mirrored: Tensor) -> tuple[Tensor, Tensor]:
        """The sensor stage of a physical-prior network: what belongs to the photodiodes, not to the lens, so it does
        not turn with the CoC's sign. Each photodiode's view is ``g (1 - k) own + k other``: a per-channel gain
        ``g = exp(p_g(x, y))`` and a crosstalk ``k = p_k(x, y)`` from the other photodiode, each a quadratic in the
        field position (:data:`FIELD_TERMS`; all coefficients start at 0: the identity, exactly). An item mirrored
        by the augmentation (``mirrored`` (B, 1, H, W) bool) shows the right photodiode as its left view at field
        ``-x``: it gets the other photodiode's stage, evaluated there."""
        x, y = field[:, 0:1], field[:, 1:2]
        xm = torch.where(mirrored, -x, x)
        terms = torch.cat([torch.ones_like(x), xm, y, xm * xm, xm * y, y * y], dim=1)  # (B, T, H, W)

        def stage(v: int) -> tuple[Tensor, Tensor]:
            g = torch.exp(torch.einsum("ct,bthw->bchw", self.sensor_gain[v], terms))
            k = torch.einsum("t,bthw->bhw", self.sensor_xtalk[v], terms)[:, None]
            return g, k

        (g0, k0), (g1, k1) = stage(0), stage(1)
        g_l, k_l = torch.where(mirrored, g1, g0), torch.where(mirrored, k1, k0)
        g_r, k_r = torch.where(mirrored, g0, g1), torch.where(mirrored, k0, k1)
        return g_l * (left + k_l * (right - left)), g_r * (right + k_r * (left - right))


def box_prefilter(x: Tensor, d: int) -> Tensor:
    """Centred separable box of width ``d`` px (replicate padding), the pre-filter of a dilation-``d`` kernel.

    For even ``d`` the 1-D filter is ``[1/2, 1, ..., 1, 1/2] / d`` (``d + 1`` taps; a width-``d`` box convolved
    with a 2-tap average, so it stays centred); for odd ``d`` it is ``d`` taps of ``1 / d``. Either way its
    copies shifted by multiples of ``d`` sum to 1, so the taps of a dilated kernel applied after it tile
    the plane without gaps or overlaps.

    Args:
        x: (B, C, H, W) image.
        d: width in px (>= 1; 1 returns ``x``).

    Returns:
        (B, C, H, W).

    Example:
        >>> y = box_prefilter(torch.ones(1, 1, 6, 6), 4)
        >>> bool(torch.allclose(y, torch.ones_like(y)))
        True
    """
    if d <= 1:
        return x
    if d % 2 == 0:
        taps = torch.ones(d + 1, dtype=x.dtype, device=x.device)
        taps[0] = taps[-1] = 0.5
    else:
        taps = torch.ones(d, dtype=x.dtype, device=x.device)
    taps = taps / d
    n, r, C = taps.numel(), taps.numel() // 2, x.shape[1]
    xp = F.pad(x, (r, r, r, r), mode="replicate")
    xp = F.conv2d(xp, taps.view(1, 1, 1, n).expand(C, 1, 1, n), groups=C)
    return F.conv2d(xp, taps.view(1, 1, n, 1).expand(C, 1, n, 1), groups=C)


def extend_multiscale(net: UNetKPN, levels: int = 2) -> UNetKPN:
    """A multi-scale copy of a trained single-scale network whose output is exactly the original's.

    Every existing weight is copied; the new scale head starts as copies of the base kernel head with zero
    blend weights (:meth:`UNetKPN.init_scales_from_base`), so fine-tuning starts from the trained model.

    Args:
        net: a network with ``multiscale_levels == 0``.
        levels: extra scales (dilations 2, 4, ..., 2**levels px).

    Returns:
        A new :class:`UNetKPN` on ``net``'s device and dtype, in ``net``'s train/eval mode.
    """
    if net.cfg.multiscale_levels:
        raise BadInputError("the network is already multi-scale", where="extend_multiscale")
    if levels < 1:
        raise BadInputError(f"levels must be >= 1, got {levels}", where="extend_multiscale")
    p = next(net.parameters())
    ext = UNetKPN(replace(net.cfg, multiscale_levels=int(levels))).to(device=p.device, dtype=p.dtype)
    missing, unexpected = ext.load_state_dict(net.state_dict(), strict=False)
    if unexpected or any(not k.startswith("scale_head.") for k in missing):
        raise BadInputError(f"state dicts do not match: missing {missing}, unexpected {unexpected}", where="extend_multiscale")
    ext.init_scales_from_base()
    ext.train(net.training)
    return ext


PRIORS = ("none", "physical")

FIELD_TERMS = ("1", "x", "y", "x^2", "xy", "y^2")
"""The terms of the quadratic field polynomials of a physical-prior network's sensor stage (:meth:`UNetKPN.sensor`)."""
"""What a network can start from (:attr:`ModelConfig.prior`)."""

SIGN_SOFTNESS_PX = 0.5
"""Width (px of CoC) over which a physical-prior network's correction turns from the behind-focus to the in-front
form (:func:`sign_weight`)."""


def sign_weight(coc_px: Tensor) -> Tensor:
    """:math:`s = (1 + \\tanh(C / 0.5\\,px)) / 2`: 1 behind focus, 0 in front of it, 1/2 in focus; ``s(-C) = 1 - s(C)``,
    so swapping the views and the CoC's sign swaps what the network's view "a" and view "b" are."""
    return 0.5 * (1.0 + torch.tanh(coc_px / SIGN_SOFTNESS_PX))


def mirror_by_sign(k: Tensor, s: Tensor) -> Tensor:
    """The left view's correction kernels from the network's kernels ``k`` for view "a" (B, K*K, H, W) or
    (B, 3, K*K, H, W): ``s k + (1 - s) hflip(k)`` with ``s`` (B, 1, H, W) from :func:`sign_weight`."""
    s = s[:, None] if k.ndim == 5 else s
    return s * k + (1 - s) * flip_lr(k)


def correction(x: Tensor, k: Tensor, dilation: int = 1) -> Tensor:
    """``sum_t k_t (S_t x - x)``: an affine per-pixel correction of ``x`` (B, C, H, W) by free kernel weights ``k``
    (B, K*K, H, W) or (B, C, K*K, H, W) (taps ``dilation`` px apart); exactly 0 where ``k`` is 0, and it keeps a flat
    region's brightness whatever ``k`` is."""
    total = k.sum(2) if k.ndim == 5 else k.sum(1, keepdim=True)
    return apply_kernels(x, k, dilation=dilation) - total * x


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
