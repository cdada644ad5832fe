"""The Neural DP Simulator behind the common :class:`DPSimulator` interface (tiled inference)."""

from __future__ import annotations

import os
from dataclasses import fields
from typing import Any

import torch
from torch import Tensor

from dp5k_common.errors import BadInputError
from dp5k_learn.batch import DPBatch

from ..model import ModelConfig, UNetKPN, normalize_depth
from .interface import DPSimulator


def model_inputs(batch: DPBatch, coc_scale_px: float) -> Tensor:
    """The network input (B, 5, H, W): sharp, CoC / coc_scale_px (0 where invalid), normalised depth."""
    coc = torch.where(batch.valid, batch.coc_px, torch.zeros_like(batch.coc_px)) / coc_scale_px
    return torch.cat([batch.sharp, coc, normalize_depth(batch.depth_mm, batch.valid)], dim=1)


def _spans(n: int, tile: int) -> list[tuple[int, int]]:
    return [(s, min(s + tile, n)) for s in range(0, n, tile)]


class NeuralDPSimulator(DPSimulator):
    """U-Net kernel-prediction DP simulator (Sec. 4.1); see :mod:`neural_dp.model`.

    Args:
        cfg: network configuration.
        net: an existing network (e.g. during training); built from ``cfg`` when None.
    """

    name = "neural"

    def __init__(self, cfg: ModelConfig | None = None, net: UNetKPN | None = None) -> None:
        super().__init__()
        self.cfg = cfg or (net.cfg if net is not None else ModelConfig())
        self.net = net if net is not None else UNetKPN(self.cfg)

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike[str], map_location: str | torch.device = "cpu") -> NeuralDPSimulator:
        """Load a checkpoint written by ``dp5k train`` (safely: ``weights_only=True``)."""
        if not os.path.isfile(path):
            raise BadInputError("checkpoint not found", where=path)
        try:
            state: dict[str, Any] = torch.load(path, map_location=map_location, weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unpickling problem is a bad file
            raise BadInputError(f"not a readable dp5k checkpoint ({type(exc).__name__}: {exc})", where=path) from exc
        if not isinstance(state, dict) or "model" not in state or "model_config" not in state:
            raise BadInputError("not a dp5k Neural DP checkpoint (no 'model' / 'model_config')", where=path)
        known = {f.name for f in fields(ModelConfig)}
        cfg = ModelConfig(**{k: v for k, v in state["model_config"].items() if k in known})
        sim = cls(cfg)
        sim.net.load_state_dict(state["model"])
        sim.eval()
        return sim

    def forward(self, batch: DPBatch) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        inputs = model_inputs(batch, self.cfg.coc_scale_px)
        H, W = batch.sharp.shape[-2:]
        tile = self.cfg.tile_px
        whole_image_norm = self.cfg.norm == "group"  # GroupNorm's statistics span the image: tiles would differ
        if self.training or whole_image_norm or tile <= 0 or (H <= tile and W <= tile):
            return self.net(batch.sharp, inputs)
        return self._forward_tiled(batch.sharp, inputs, tile, self.cfg.tile_margin_px)

    def _forward_tiled(self, sharp: Tensor, inputs: Tensor, tile: int, margin: int) -> tuple[Tensor, Tensor]:
        """Predict tile by tile with ``margin`` px of context; peak memory is set by the tile, not the image.

        Tile origins and margins are multiples of the U-Net's down-sampling factor, so every tile sees the
        same pooling grid as the whole image. The margin is raised to the network's receptive radius
        (:attr:`~neural_dp.model.UNetKPN.receptive_radius_px`), so (with BatchNorm in eval mode, which is
        local) the stitched result equals the whole-image result.

        Args:
            sharp: (B, 3, H, W) linear image. inputs: (B, 5, H, W) network input.
            tile: tile side, px (rounded down to a multiple of ``2 ** levels``).
            margin: context, px (raised to the receptive radius, rounded up to a multiple of ``2 ** levels``).

        Returns:
            (left, right), each (B, 3, H, W).
        """
        m = self.net.multiple
        tile = max(m, tile // m * m)
        margin = -(-max(margin, self.net.receptive_radius_px) // m) * m
        H, W = sharp.shape[-2:]
        left = torch.empty_like(sharp)
        right = torch.empty_like(sharp)
        for y0, y1 in _spans(H, tile):
            for x0, x1 in _spans(W, tile):
                ya, yb = max(0, y0 - margin), min(H, y1 + margin)
                xa, xb = max(0, x0 - margin), min(W, x1 + margin)
                l, r = self.net(sharp[..., ya:yb, xa:xb], inputs[..., ya:yb, xa:xb])
                left[..., y0:y1, x0:x1] = l[..., y0 - ya : y1 - ya, x0 - xa : x1 - xa]
                right[..., y0:y1, x0:x1] = r[..., y0 - ya : y1 - ya, x0 - xa : x1 - xa]
        return left, right
