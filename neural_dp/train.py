"""Train the Neural DP Simulator (Sec. 5.1): Eq. (8)/(9) loss, Adam + cosine annealing, best-by-val-SSIM.

This module holds only what is the Neural DP Simulator's own: its forward pass (:func:`forward_fn`), its loss
(Eq. (8) on the valid mask minus the kernels' reach, :func:`loss_fn`), its validation score and the data-driven
initialisation of its view gains. The run's set-up (Adam, schedule, sampler, loader, DDP, AMP), the optimiser
step and the epoch loop are :mod:`dp5k_learn`'s, shared with ``dp5k deblur train``.

:func:`train` runs in a single process (CPU by default, CUDA when present) or as one of many processes under
``torchrun`` (DistributedDataParallel; see :mod:`dp5k_learn.distributed`). It writes into ``out_dir``:

* ``config.json``: the resolved configuration;
* ``last.pt``: everything needed to resume, rewritten atomically after every epoch;
* ``best.pt``: the weights with the highest validation masked SSIM so far (what ``dp5k evaluate`` uses);
* ``history.json``: per-epoch loss, validation metrics, learning rate and throughput.

Running the same command again resumes from ``last.pt`` (epoch granularity; the data and dropout of
every epoch are seeded by ``(seed, epoch, rank)``, so a resumed run reproduces an uninterrupted one).

:func:`finetune` trains an existing simulator for a fixed number of steps, without epochs or checkpoints
(:class:`~dp5k_learn.config.FinetuneConfig`), with the same step.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from dp5k_common.sharding import RankInfo
from dp5k_learn import training
from dp5k_learn.batch import DPBatch
from dp5k_learn.config import FinetuneConfig
from dp5k_learn.data import DPPairDataset
from dp5k_learn.epochs import EpochLoop, TrainResult, run_epochs
from dp5k_learn.losses import dp_loss
from dp5k_learn.metrics import view_metrics
from dp5k_learn.training import Forward, Loss

from .config import TrainConfig
from .model import ModelConfig
from .simulators.neural import NeuralDPSimulator, model_inputs


def loss_mask(valid: torch.Tensor, border_px: int) -> torch.Tensor:
    """Valid depth minus a ``border_px`` frame (the kernels' replicate padding is not data). (B,1,H,W) float."""
    m = valid.float()
    if border_px > 0:
        m[..., :border_px, :] = 0
        m[..., -border_px:, :] = 0
        m[..., :, :border_px] = 0
        m[..., :, -border_px:] = 0
    return m


@torch.no_grad()
def init_view_gain(sim: NeuralDPSimulator, ds: DPPairDataset, max_pairs: int = 16) -> torch.Tensor:
    """Set the per-view, per-channel gains to the data's mean view / sharp ratio over valid pixels. Returns (2, 3)."""
    sums = torch.zeros(3, 3, dtype=torch.float64)
    for pid in ds.ids[:max_pairs]:
        pair = ds.pair(pid)
        v = pair.valid[..., None]
        sums[0] += torch.from_numpy((pair.sharp * v).sum((0, 1)).astype(np.float64))
        sums[1] += torch.from_numpy((pair.left * v).sum((0, 1)).astype(np.float64))
        sums[2] += torch.from_numpy((pair.right * v).sum((0, 1)).astype(np.float64))
    gain = (sums[1:] / sums[0].clamp_min(1e-12)).clamp(0.05, 2.0).float()
    sim.net.view_gain.copy_(gain)
    return gain


def forward_fn(net: nn.Module, coc_scale_px: float) -> Forward:
    """The network's forward pass on a batch: ``(left, right)`` from the sharp image and :func:`model_inputs`.
    ``net`` is the network or its DistributedDataParallel wrapper."""
    return lambda batch: net(batch.sharp, model_inputs(batch, coc_scale_px))


def loss_fn(border_px: int, grad_weight: float) -> Loss:
    """Eq. (8) on the valid mask minus a ``border_px`` frame (:func:`loss_mask`), in float32."""
    def loss(views: tuple[Tensor, Tensor], batch: DPBatch) -> Tensor:
        left, right = views
        return dp_loss(left.float(), right.float(), batch.left, batch.right, loss_mask(batch.valid, border_px), grad_weight)

    return loss


def score(sim: NeuralDPSimulator) -> training.Score:
    """Masked SSIM / PSNR / MAE of the simulated views (mean of L and R) against the measured ones."""
    def of(batch: DPBatch) -> dict[str, Tensor]:
        left, right = sim(batch)
        return view_metrics(left.float(), right.float(), batch.left, batch.right, batch.valid)

    return of


def validate(sim: NeuralDPSimulator, ds: DPPairDataset, info: RankInfo, device: torch.device,
             max_pairs: int = 0) -> dict[str, float]:
    """Masked SSIM / PSNR / MAE (mean of L and R, mean over pairs) on full-resolution pairs, sharded over processes
    (:func:`dp5k_learn.training.validate_pairs`)."""
    return training.validate_pairs(sim, ds, score(sim), info, device, max_pairs)


NEW_PARAMETER_PREFIX = "scale_head."
"""Parameters a structural extension adds to a trained network (:func:`neural_dp.model.extend_multiscale`);
:func:`finetune` trains them at ``FinetuneConfig.new_lr_mult`` times the rate."""


def finetune(sim: NeuralDPSimulator, dataset: str | os.PathLike[str], cfg: FinetuneConfig, device: torch.device | str = "cpu",
             desc: str = "fine-tune") -> list[float]:
    """Fine-tune a simulator in place on ``dataset``'s train crops for exactly ``cfg.steps`` optimiser steps
    (:func:`dp5k_learn.training.finetune`): the loss of ``dp5k train`` with a ``cfg.border_px`` border (None = the
    network's kernel reach); parameters named ``scale_head.*`` at ``cfg.new_lr_mult`` times the rate.

    Returns:
        The loss of every step (length ``cfg.steps``); ``sim`` is left in eval mode.

    Raises:
        EmptySplitError: the train split is empty.
        StageError: the loss became NaN.
    """
    border = sim.net.reach_px if cfg.border_px is None else int(cfg.border_px)
    sim.to(device)
    losses = training.finetune(sim.net, dataset, cfg, forward_fn(sim.net, sim.cfg.coc_scale_px),
                               loss_fn(border, cfg.grad_weight), device=device,
                               is_new=lambda name: name.startswith(NEW_PARAMETER_PREFIX), desc=desc)
    sim.eval()
    return losses


def train(dataset: str | os.PathLike[str], out_dir: str | os.PathLike[str], cfg: TrainConfig, *, resume: bool = True,
          on_epoch_end: Callable[[int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train (or resume training) the Neural DP Simulator on ``dataset``'s train split.

    Args:
        dataset: a format-v1 dataset (train and val splits are used).
        out_dir: where checkpoints, config and history go (created).
        cfg: the run's configuration.
        resume: continue from ``out_dir/last.pt`` when it exists.
        on_epoch_end: called as ``on_epoch_end(epoch, record)`` after each epoch's checkpoint is written.

    Returns:
        A :class:`TrainResult`.

    Raises:
        BadInputError / DatasetFormatError: unusable dataset or config.
        StageError: the loss became NaN.
    """
    with training.joined(cfg.device) as (info, device):
        return _train(Path(dataset), Path(out_dir), cfg, info, device, resume, on_epoch_end)


def _train(root: Path, out: Path, cfg: TrainConfig, info: RankInfo, device: torch.device, resume: bool,
           on_epoch_end: Callable[[int, dict[str, float]], None] | None) -> TrainResult:
    out.mkdir(parents=True, exist_ok=True)
    train_ds, val_ds = training.open_splits(root, cfg.data, cfg.seed)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed % (2**32))
    sim = NeuralDPSimulator(cfg.model).to(device)
    run = training.build_run(sim.net, train_ds, cfg.data, cfg.optim, cfg.seed, info, device)
    border = sim.net.reach_px  # K // 2, more with multi-scale kernels
    loop = EpochLoop(run=run, forward=forward_fn(run.net, cfg.model.coc_scale_px), loss=loss_fn(border, cfg.optim.grad_weight),
                     validate=lambda: validate(sim, val_ds, info, device, cfg.data.val_pairs), model_config=asdict(cfg.model),
                     config=cfg.to_dict(), defaults=asdict(ModelConfig()))
    return run_epochs(loop, out, resume=resume, on_fresh_start=lambda: init_view_gain(sim, train_ds), on_epoch_end=on_epoch_end)
