"""The Neural DP Simulator behind the common :class:`DPSimulator` interface (tiled inference).

With a physical prior (``ModelConfig.prior = "physical"``, :mod:`neural_dp.model`) the simulator first renders the
physical model its checkpoint names (``ModelConfig.prior_spec``) on the whole image, then runs the network over it.
Like the base model it has free parameters that ``dp5k evaluate`` fits on the train pairs of the dataset it scores
(:meth:`NeuralDPSimulator.fit`): the physical model's rim softness and gain, fitted exactly as ``base`` is, and the
strength of the learned correction, in [0, 1] (0 = the physical model exactly).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import fields
from typing import Any

import torch
from torch import Tensor

from dp5k_common.errors import BadInputError
from dp5k_learn.batch import DPBatch

from ..model import ModelConfig, UNetKPN, normalize_depth
from .base import BaseModel, field_coords
from .base.spec import model_from_spec
from .interface import DPSimulator

logger = logging.getLogger(__name__)


def model_inputs(batch: DPBatch, coc_scale_px: float) -> Tensor:
    """The network input (B, 5, H, W): sharp, CoC / coc_scale_px (0 where invalid), normalised depth."""
    coc = torch.where(batch.valid, batch.coc_px, torch.zeros_like(batch.coc_px)) / coc_scale_px
    return torch.cat([batch.sharp, coc, normalize_depth(batch.depth_mm, batch.valid)], dim=1)


def physical_inputs(batch: DPBatch, prior_left: Tensor, prior_right: Tensor) -> Tensor:
    """The input (B, 11, H, W) of a physical-prior network (:attr:`~neural_dp.model.UNetKPN.physical_inputs`): the
    physical views, the signed CoC in px (0 where invalid), the valid mask, the pixels' field position (the batch's
    ``field``, else each item as a whole frame) and whether an item is mirrored."""
    B, _, H, W = batch.sharp.shape
    dev, dt = batch.sharp.device, batch.sharp.dtype
    valid = batch.valid.to(dt)
    coc = torch.where(batch.valid, batch.coc_px, torch.zeros_like(batch.coc_px)).to(dt)
    field = batch.field.to(dt) if batch.field is not None else field_coords(B, H, W, dev).to(dt)
    mirrored = (batch.mirrored.to(dt).view(B, 1, 1, 1) if batch.mirrored is not None else torch.zeros(B, 1, 1, 1, device=dev, dtype=dt))
    return torch.cat([prior_left.to(dt), prior_right.to(dt), coc, valid, field, mirrored.expand(B, 1, H, W)], dim=1)


def build_prior(cfg: ModelConfig) -> BaseModel:
    """The physical model a physical-prior network corrects: ``cfg.prior_spec`` rebuilt, or the base model at its
    defaults when the spec is empty.

    Raises:
        BadInputError: a spec that is not JSON or not a model spec.
    """
    if not cfg.prior_spec:
        return BaseModel().eval()
    try:
        spec = json.loads(cfg.prior_spec)
    except json.JSONDecodeError as exc:
        raise BadInputError(f"model.prior_spec is not JSON ({exc})", where="ModelConfig") from exc
    return model_from_spec(spec).eval()


CV_STRIPS = 4
"""Vertical strips each fit crop is cut into for the correction's spatial cross-validation (:meth:`NeuralDPSimulator.fit`)."""

Unit = tuple[str, int]
"""A cross-validation unit: (pair id, strip)."""


def cross_validated_scale(num: dict[Unit, float], den: dict[Unit, float], base_sse: dict[Unit, float]
                          ) -> tuple[float, dict[str, float]]:
    r"""The correction's strength ``a`` in [0, 1], kept only where it predicts data it was not fitted on.

    Per unit ``u`` (a vertical strip of one pair's crops), with the correction ``d = network - physical`` and the
    error ``e = measured - physical`` over its valid pixels: ``num_u = sum d e``, ``den_u = sum d^2``,
    ``base_sse_u = sum e^2``. The least-squares scale is :math:`a = \mathrm{clip}(\sum num / \sum den, 0, 1)`; at
    scale ``a`` a group's squared error changes by :math:`a^2 den_G - 2 a\, num_G`. Two cross-validations, each
    scoring every group at the scale fitted on the others: leave one **pair** out, and leave one **strip** out (the
    same strip of every pair: a correction that helps in one part of the frame and harms the rest does not carry
    to the parts it was not fitted on, such as those a crop leaves out). Where either sums to no drop of
    the held-out squared error, ``a`` is 0: the physical model.

    Returns:
        (a, gains): ``gains["pairs"]``, ``gains["strips"]``, each the held-out squared error's relative drop,
        :math:`-\sum_G \Delta_G / \sum base\_sse` (absent where there are fewer than 2 groups: nothing to hold out).
    """
    N, D = sum(num.values()), sum(den.values())
    a = min(1.0, max(0.0, N / D)) if D > 0 else 1.0
    total = sum(base_sse.values())
    gains: dict[str, float] = {}
    for label, group in (("pairs", lambda u: u[0]), ("strips", lambda u: u[1])):
        gn: dict[Any, float] = {}
        gd: dict[Any, float] = {}
        for u in num:
            gn[group(u)] = gn.get(group(u), 0.0) + num[u]
            gd[group(u)] = gd.get(group(u), 0.0) + den[u]
        if len(gn) < 2:
            continue
        change = 0.0
        for g in gn:
            n, d = N - gn[g], D - gd[g]
            a_g = min(1.0, max(0.0, n / d)) if d > 0 else 0.0
            change += a_g * a_g * gd[g] - 2.0 * a_g * gn[g]
        gains[label] = -change / total if total > 0 else 0.0
    return (a if all(g > 0 for g in gains.values()) else 0.0), gains


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
        self.prior: BaseModel | None = build_prior(self.cfg) if self.cfg.prior == "physical" else None
        self.correction_scale = 1.0
        """How much of the learned correction a physical-prior simulator applies (1 = all of it; :meth:`fit`)."""

    @property
    def physical(self) -> bool:
        """True when the network corrects a physical model (``ModelConfig.prior = "physical"``)."""
        return self.prior is not None

    @torch.no_grad()
    def prior_views(self, batch: DPBatch) -> tuple[Tensor, Tensor]:
        """The physical model's (left, right) for ``batch``: the batch's own ``prior_left`` / ``prior_right`` when a
        trainer rendered them, else rendered now, on the whole batch exactly as the ``base`` simulator renders it."""
        if self.prior is None:
            raise BadInputError("this Neural DP network has no physical prior", where="NeuralDPSimulator")
        if batch.prior_left is not None and batch.prior_right is not None:
            return batch.prior_left, batch.prior_right
        left, right = self.prior(batch)
        return left.to(batch.sharp.dtype), right.to(batch.sharp.dtype)

    def _fit_start(self) -> dict[str, float]:
        """Where :meth:`fit` starts the physical model's fit: the spec's ``fit_start`` (what ``dp5k train`` fitted from:
        the base model's defaults, or a diagnose report's values), else its current values."""
        spec = json.loads(self.cfg.prior_spec) if self.cfg.prior_spec else {}
        return {k: float(v) for k, v in spec.get("fit_start", {}).items()}

    def inputs(self, batch: DPBatch) -> Tensor:
        """The network's input for ``batch`` (:func:`model_inputs`, or :func:`physical_inputs` with the physical views)."""
        if self.prior is None:
            return model_inputs(batch, self.cfg.coc_scale_px)
        return physical_inputs(batch, *self.prior_views(batch))

    def fit(self, batches: list[DPBatch]) -> dict[str, float]:  # type: ignore[override]
        """With a physical prior: fit its rim softness and gain on ``batches`` exactly as the base model is fitted
        (:meth:`BaseModel.fit`), then the strength of the correction, :attr:`correction_scale` in [0, 1], by least
        squares over the batches' valid pixels (closed form: the views are affine in it). ``dp5k evaluate`` calls
        this with the train crops of the dataset it scores, so on a camera whose train pairs the correction does
        not fit the simulator falls back towards the physical model. The paper's network has nothing to fit.

        The correction is kept only where it predicts data it was not fitted on (:func:`cross_validated_scale`:
        leave one pair out, and leave one vertical strip of every crop out). In the demo a scale of 0.14, fitted on
        crops where it lowered the squared error by 1-3 %, raised it by 1-7 % on the whole frames of the same pairs:
        it helped in one band of columns and harmed the rest.

        Returns:
            The fitted values by name (empty for the paper's network), with ``correction_cv_gain_pairs`` and
            ``correction_cv_gain_strips``, each cross-validation's relative drop of the held-out squared error.
        """
        if self.prior is None or not batches:
            return {}
        self.prior.params.update(self._fit_start())  # the start of the base fit in evaluate: the same fit, the same result
        fitted = self.prior.fit(batches)
        num: dict[Unit, float] = {}
        den: dict[Unit, float] = {}
        base_sse: dict[Unit, float] = {}
        self.correction_scale = 1.0
        was_training = self.training
        self.eval()
        with torch.no_grad():
            for b in batches:
                pl, pr = self.prior_views(b)
                left, right = self._network(b, pl, pr)
                m = b.valid.to(left.dtype)
                ids = list(b.pair_ids) if b.pair_ids else [f"batch{id(b)}_{i}" for i in range(b.sharp.shape[0])]
                for out, p, target in ((left, pl, b.left), (right, pr, b.right)):
                    d = (out - p) * m
                    e = (target - p) * m
                    # (3, B, CV_STRIPS): sum d e, sum d^2, sum e^2 over each vertical strip of each item
                    strips = torch.stack([torch.stack([c.sum((1, 2, 3)) for c in t.tensor_split(CV_STRIPS, dim=-1)], -1)
                                          for t in (d * e, d * d, e * e)]).tolist()
                    for acc, per_item in zip((num, den, base_sse), strips):
                        for pid, row in zip(ids, per_item):
                            for k, v in enumerate(row):
                                acc[(pid, k)] = acc.get((pid, k), 0.0) + v
        self.train(was_training)
        self.correction_scale, gains = cross_validated_scale(num, den, base_sse)
        return {**fitted, "correction_scale": self.correction_scale, **{f"correction_cv_gain_{k}": v for k, v in gains.items()}}

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
        with torch.random.fork_rng(devices=[]):  # the initial weights are overwritten: draw them from no one's generator
            sim = cls(cfg)
        sim.net.load_state_dict(state["model"])
        sim.eval()
        return sim

    def forward(self, batch: DPBatch) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        if self.prior is None:
            return self._network(batch)
        pl, pr = self.prior_views(batch)
        left, right = self._network(batch, pl, pr)
        a = self.correction_scale
        if a == 1.0:
            return left, right
        return pl + a * (left - pl), pr + a * (right - pr)

    def _network(self, batch: DPBatch, prior_left: Tensor | None = None, prior_right: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The network's views (the whole correction, whatever :attr:`correction_scale` is), tiled at inference."""
        inputs = (model_inputs(batch, self.cfg.coc_scale_px) if prior_left is None
                  else physical_inputs(batch, prior_left, prior_right))
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
