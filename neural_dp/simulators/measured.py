"""The measured simulator: a camera's own DP kernels, from a ``dp5k diagnose`` PSF atlas (``measured:ATLAS``).

``atlas.npz`` (docs/data-format.md, "The PSF atlas") holds the kernels ``dp5k diagnose`` measured from a dataset's
views, per view (L, R), colour channel and signed CoC bin over the whole field, and per field zone at coarser bins.
This simulator renders with them:

* **CoC.** Each measured whole-field bin is a node at its pixels' mean CoC. Every sharp pixel spreads its light
  with the kernels of the two nodes around its CoC, weighted linearly between them (the nearest at either end: the
  atlas says nothing beyond its range): ``view = sum_j K_j * (w_j sharp)`` with hat weights ``w_j`` of the CoC map,
  each node's convolution by FFT over the frame. Light is conserved (no compositing): each kernel is rescaled to its
  cell's measured DC gain, so each view keeps its measured brightness.
* **Channels.** Each colour channel renders with its own kernels (longitudinal colour).
* **Field.** The views' L/R brightness varies over the field as the atlas's field zones measured it: each zone's
  DC gain against the whole field's, bilinear over the zones' centres. The kernels' shape over the field is not
  interpolated (the zones' kernels are measured at coarse bins; the whole field's are used everywhere).

Unlike a parametric model it needs no vocabulary: what the camera does within the atlas's CoC range, it does. It
does not know occlusion (kernels come from pixels away from depth edges, and each pixel's light spreads over its
neighbours whatever their depth, as in a scatter renderer).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy.fft import next_fast_len
from torch import Tensor

from dp5k_common.errors import BadInputError
from dp5k_learn.batch import DPBatch

from .interface import DPSimulator

ATLAS_FORMAT = "dp5k-atlas"


def _load(path: Path) -> dict[str, np.ndarray]:
    try:
        z = np.load(path, allow_pickle=False)
        data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise BadInputError(f"cannot read the PSF atlas ({exc})", where=path) from exc
    if str(data.get("format", "")) != ATLAS_FORMAT:
        raise BadInputError("not a dp5k PSF atlas (no format 'dp5k-atlas'; 'dp5k diagnose' writes atlas.npz)", where=path)
    return data


class MeasuredSimulator(DPSimulator):
    """Renders with the kernels of a PSF atlas's ``view_set`` (default ``measured``): module docstring.

    Args:
        atlas: path of an ``atlas.npz``.
        view_set: which of its kernel sets (``measured``, or ``simulator`` / ``extended`` to render as those did).
    """

    name = "measured"

    def __init__(self, atlas: str | os.PathLike[str], view_set: str = "measured") -> None:
        super().__init__()
        self.path = Path(atlas)
        if not self.path.is_file():
            raise BadInputError("PSF atlas not found", where=self.path)
        z = _load(self.path)
        names = [str(n) for n in z["view_sets"]]
        if view_set not in names:
            raise BadInputError(f"the atlas has no view-set {view_set!r} (it has {', '.join(names)})", where=self.path)
        v = names.index(view_set)
        cells = z["cells"]
        nodes, kernels = [], []
        for row, (b, zone, h, bs, measured) in enumerate(cells):
            if zone >= 0 or not measured or f"kernel_{row}" not in z:
                continue
            k = z[f"kernel_{row}"][v].astype(np.float64)  # (2, 3, K, K)
            sums = k.sum((-1, -2))
            gain = z["dc_gain"][row, v]  # (2, 3)
            k = k * np.where(np.abs(sums) > 1e-9, gain / np.where(np.abs(sums) > 1e-9, sums, 1.0), 1.0)[..., None, None]
            nodes.append(float(z["cell_coc_px"][row, 2]))
            kernels.append(k)
        if len(nodes) < 2:
            raise BadInputError(f"the atlas measured {len(nodes)} whole-field CoC bin(s) of {view_set!r}; 2 are needed", where=self.path)
        order = np.argsort(nodes)
        self.nodes = np.asarray(nodes)[order]
        size = max(k.shape[-1] for k in kernels)
        self.kernels = np.stack([_pad(kernels[i], size) for i in order])  # (n, 2, 3, K, K)
        self.zone_gain = _zone_gains(z, v)  # (zones, zones, 2, 3) relative to the whole field, or None

    def forward(self, batch: DPBatch) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        sharp = batch.sharp
        B, C, H, W = sharp.shape
        dt, dev = sharp.dtype, sharp.device
        K = self.kernels.shape[-1]
        r = K // 2
        Hp, Wp = next_fast_len(H + 2 * r, real=True), next_fast_len(W + 2 * r, real=True)
        nodes = torch.as_tensor(self.nodes, dtype=dt, device=dev)
        c = torch.where(batch.valid, batch.coc_px, torch.zeros_like(batch.coc_px))[:, 0].clamp(float(self.nodes[0]), float(self.nodes[-1]))
        j = torch.bucketize(c, nodes).clamp(1, len(self.nodes) - 1)
        t = (c - nodes[j - 1]) / (nodes[j] - nodes[j - 1]).clamp_min(1e-9)  # (B, H, W)
        out = torch.zeros(B, 2, C, Hp, Wp // 2 + 1, dtype=torch.complex64 if dt == torch.float32 else torch.complex128, device=dev)
        for n in torch.unique(torch.cat([j - 1, j])).tolist():
            w = torch.where(j - 1 == n, 1 - t, torch.zeros_like(t)) + torch.where(j == n, t, torch.zeros_like(t))
            if not bool((w > 0).any()):
                continue
            src = torch.fft.rfft2(sharp * w[:, None], s=(Hp, Wp))  # (B, C, Hp, Wf)
            k = torch.as_tensor(self.kernels[n], dtype=dt, device=dev)  # (2, C, K, K)
            big = torch.zeros(2, C, Hp, Wp, dtype=dt, device=dev)
            big[..., :K, :K] = k
            spec = torch.fft.rfft2(torch.roll(big, shifts=(-r, -r), dims=(-2, -1)))  # the kernel centred at (0, 0)
            out += src[:, None] * spec[None]
        views = torch.fft.irfft2(out, s=(Hp, Wp))[..., :H, :W]  # linear convolution: the wrap lands in the padding
        left, right = views[:, 0], views[:, 1]
        if self.zone_gain is not None:
            g = _field_gain(self.zone_gain, batch, left.dtype)  # (B, 2, 3, H, W)
            left, right = left * g[:, 0], right * g[:, 1]
        return left, right



def _pad(k: np.ndarray, size: int) -> np.ndarray:
    p = (size - k.shape[-1]) // 2
    return np.pad(k, [(0, 0)] * (k.ndim - 2) + [(p, p), (p, p)]) if p else k


def _zone_gains(z: dict[str, np.ndarray], v: int) -> np.ndarray | None:
    """(zones, zones, 2, 3): each field zone's DC gain (its bins pooled by pixels) over the whole field's, per view and
    channel; None when fewer than 2 zones were measured."""
    cells, pix, gain = z["cells"], z["cell_pixels"], z["dc_gain"][:, v]
    n = int(z["zones"])
    whole = cells[:, 1] < 0
    ref = (gain[whole] * pix[whole, None, None]).sum(0) / max(pix[whole].sum(), 1e-9)
    out = np.ones((n, n, 2, 3))
    seen = 0
    for zone in range(n * n):
        sel = cells[:, 1] == zone
        if pix[sel].sum() <= 0 or not np.isfinite(gain[sel]).all():
            continue
        zy, zx = divmod(zone, n)
        out[zy, zx] = (gain[sel] * pix[sel, None, None]).sum(0) / pix[sel].sum() / np.where(ref > 0, ref, 1.0)
        seen += 1
    return out if seen >= 2 else None


def _field_gain(zone_gain: np.ndarray, batch: DPBatch, dtype: torch.dtype) -> Tensor:
    """(B, 2, 3, H, W) the zones' relative gains, bilinear over the zones' centres at each pixel's field position
    (the batch is whole frames; field coordinates in [-1, 1])."""
    B, _, H, W = batch.sharp.shape
    n = zone_gain.shape[0]
    g = torch.as_tensor(zone_gain, dtype=dtype, device=batch.sharp.device).permute(2, 3, 0, 1).reshape(1, 6, n, n)
    # zone centres sit at (2 i + 1) / n - 1; align_corners=False on an n x n grid puts them exactly there
    up = F.interpolate(g, size=(H, W), mode="bilinear", align_corners=False)
    return up.reshape(1, 2, 3, H, W).expand(B, 2, 3, H, W)
