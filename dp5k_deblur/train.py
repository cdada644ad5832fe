"""Train the DP deblurrer on any format-v1 dataset: Charbonnier loss against ``sharp``, Adam + cosine annealing,
best-by-val-SSIM, resume and torchrun, all through the set-up, step and epoch loop ``dp5k train`` uses
(:mod:`dp5k_learn`). This module holds only the deblurrer's forward pass, loss and validation score.

``train_deblur`` writes into ``out_dir`` what :func:`dp5k_learn.epochs.run_epochs` writes (``config.json``,
``last.pt``, ``best.pt``, ``history.json``). With ``init_from`` a fresh run starts from another run's weights
(the paper's transfer setting: pre-train on synthetic data, fine-tune on a few real pairs).

Launch on several GPUs: ``torchrun --nproc_per_node G -m dp5k_cli deblur train DATASET --out DIR``.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path

import torch
from torch import Tensor, nn

from dp5k_common.errors import BadInputError
from dp5k_common.sharding import RankInfo
from dp5k_learn import training
from dp5k_learn.batch import DPBatch
from dp5k_learn.checkpoint import load_checkpoint
from dp5k_learn.data import DPPairDataset
from dp5k_learn.epochs import EpochLoop, TrainResult, run_epochs
from dp5k_learn.losses import CHARBONNIER_EPS, masked_charbonnier, masked_gradient_charbonnier
from dp5k_learn.metrics import masked_mae, masked_psnr, masked_ssim
from dp5k_learn.training import Forward, Loss

from .config import DeblurTrainConfig
from .model import DeblurNetConfig, DPDeblurNet


def target_mask(valid: Tensor) -> Tensor:
    """(B, 1, H, W) float: the valid-depth mask, or all ones for an item without any valid depth (a DPDD import:
    the sharp target is defined everywhere even where depth is not)."""
    v = valid.float()
    has_depth = v.flatten(1).amax(1).view(-1, 1, 1, 1) > 0
    return torch.where(has_depth, v, torch.ones_like(v))


def deblur_loss(pred: Tensor, sharp: Tensor, mask: Tensor, grad_weight: float = 0.0, eps: float = CHARBONNIER_EPS) -> Tensor:
    """Masked Charbonnier (``eps`` in linear intensity) of the prediction against ``sharp`` (plus ``grad_weight`` x
    the gradient term). Scalar."""
    loss = masked_charbonnier(pred, sharp, mask, eps)
    if grad_weight:
        loss = loss + grad_weight * masked_gradient_charbonnier(pred, sharp, mask, eps)
    return loss


def views(batch: DPBatch, where: str) -> tuple[Tensor, Tensor]:
    """The batch's (left, right) views, (B, 3, H, W). Raises BadInputError when the dataset has none."""
    if batch.left is None or batch.right is None:
        raise BadInputError("a deblurring pair needs its left and right views", where=where)
    return batch.left, batch.right


def forward_fn(net: nn.Module) -> Forward:
    """The network's forward pass on a batch: the deblurred image (B, 3, H, W) from its two views. ``net`` is the
    network or its DistributedDataParallel wrapper."""
    return lambda batch: net(*views(batch, "deblur train"))


def loss_fn(grad_weight: float, eps: float = CHARBONNIER_EPS) -> Loss:
    """:func:`deblur_loss` of the prediction (in float32) against ``sharp`` on :func:`target_mask`."""
    return lambda pred, batch: deblur_loss(pred.float(), batch.sharp, target_mask(batch.valid), grad_weight, eps)


def sharp_metrics(pred: Tensor, sharp: Tensor, valid: Tensor) -> dict[str, Tensor]:
    """Masked MAE, PSNR (dB) and SSIM of (B, 3, H, W) images against ``sharp`` (:func:`target_mask`). Each (B,)."""
    m = target_mask(valid)
    return {"mae": masked_mae(pred, sharp, m), "psnr": masked_psnr(pred, sharp, m), "ssim": masked_ssim(pred, sharp, m)}


def validate_deblur(net: DPDeblurNet, ds: DPPairDataset, info: RankInfo, device: torch.device,
                    max_pairs: int = 0) -> dict[str, float]:
    """Mean masked SSIM / PSNR / MAE of the prediction against ``sharp`` on whole val pairs, sharded over processes
    (:func:`dp5k_learn.training.validate_pairs`)."""
    def score(batch: DPBatch) -> dict[str, Tensor]:
        return sharp_metrics(net(*views(batch, "deblur validate")).float(), batch.sharp, batch.valid)

    return training.validate_pairs(net, ds, score, info, device, max_pairs)


def load_deblurrer(checkpoint: str | os.PathLike[str], device: torch.device | str = "cpu") -> DPDeblurNet:
    """A trained deblurrer from a ``dp5k deblur train`` checkpoint, in eval mode.

    Raises:
        BadInputError: missing, unreadable or not a deblurrer's checkpoint.
    """
    state = load_checkpoint(checkpoint, map_location=device)
    cfg = state.get("model_config")
    try:
        net = DPDeblurNet(DeblurNetConfig(**cfg))  # type: ignore[arg-type]
        net.load_state_dict(state["model"])
    except (TypeError, RuntimeError) as exc:
        raise BadInputError("not a deblurrer checkpoint (dp5k deblur train writes one)", where=checkpoint) from exc
    return net.to(device).eval()


def train_deblur(dataset: str | os.PathLike[str], out_dir: str | os.PathLike[str], cfg: DeblurTrainConfig, *,
                 resume: bool = True, init_from: str | os.PathLike[str] | None = None) -> TrainResult:
    """Train (or resume training) the deblurrer on ``dataset``'s train split; select by val SSIM (train when no val).

    Args:
        dataset: any format-v1 dataset (studio, synthesized, imported).
        out_dir: run folder (created).
        cfg: the run's configuration.
        resume: continue from ``out_dir/last.pt`` when it exists.
        init_from: a deblurrer checkpoint whose weights a fresh run starts from (fine-tuning).

    Raises:
        EmptySplitError: no train pairs. BadInputError: unusable checkpoint or config. StageError: NaN loss.
    """
    with training.joined(cfg.device) as (info, device):
        return _train(Path(dataset), Path(out_dir), cfg, info, device, resume, init_from)


def _train(root: Path, out: Path, cfg: DeblurTrainConfig, info: RankInfo, device: torch.device, resume: bool,
           init_from: str | os.PathLike[str] | None) -> TrainResult:
    out.mkdir(parents=True, exist_ok=True)
    train_ds, val_ds = training.open_splits(root, cfg.data, cfg.seed)
    torch.manual_seed(cfg.seed)
    net = DPDeblurNet(cfg.model).to(device)
    run = training.build_run(net, train_ds, cfg.data, cfg.optim, cfg.seed, info, device)

    def start_from_checkpoint() -> None:
        if init_from is not None:
            net.load_state_dict(load_deblurrer(init_from, device).state_dict())

    loop = EpochLoop(run=run, forward=forward_fn(run.net), loss=loss_fn(cfg.optim.grad_weight, cfg.charbonnier_eps),
                     validate=lambda: validate_deblur(net, val_ds, info, device, cfg.data.val_pairs),
                     model_config=asdict(cfg.model), defaults=asdict(DeblurNetConfig()),
                     config={**cfg.to_dict(), "init_from": None if init_from is None else str(init_from)})
    return run_epochs(loop, out, resume=resume, on_fresh_start=start_from_checkpoint, desc="deblur train")
