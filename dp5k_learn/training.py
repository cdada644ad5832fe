"""A training run's parts built from its config, the one optimiser step, validation across processes, fine-tuning.

Every trainer of dp5k (``neural_dp.train``, ``dp5k_deblur.train``) supplies only what its network does: a
**forward** pass (``forward(batch) -> output``, run under bfloat16 autocast when AMP is on) and a **loss**
(``loss(output, batch) -> scalar``, float32). Everything else is here:

* :func:`joined`: torchrun's process group and this process's device, for the length of a run;
* :func:`open_splits`: the train split (random crops) and the validation split (val, else train);
* :func:`build_run`: Adam, the per-step cosine schedule, the DistributedSampler and DataLoader, the
  DistributedDataParallel wrapper and the AMP setting, as a :class:`TrainingRun`;
* :func:`optimiser_step`: forward, loss, a finite check, backward, global gradient clipping, Adam, schedule;
* :func:`validate_pairs`: masked SSIM / PSNR / MAE on whole pairs, sharded over processes and all-reduced;
* :func:`finetune`: a fixed number of steps on train crops, without epochs or checkpoints.

The epoch loop that drives a :class:`TrainingRun` (resume, checkpoints, history) is :mod:`dp5k_learn.epochs`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, DistributedSampler

from dp5k_common.errors import EmptySplitError, StageError
from dp5k_common.progress import progress
from dp5k_common.sharding import RankInfo

from . import distributed as D
from .batch import DPBatch
from .config import DataConfig, FinetuneConfig, OptimConfig
from .data import CropSpec, DPPairDataset, collate_dp

logger = logging.getLogger(__name__)

Forward = Callable[[DPBatch], Any]
"""A network's forward pass on a batch already on its device."""
Loss = Callable[[Any, DPBatch], Tensor]
"""The scalar training loss of a forward pass's output against the batch."""
Score = Callable[[DPBatch], dict[str, Tensor]]
"""Per-pair ``{"ssim", "psnr", "mae"}``, each (B,), of the network's prediction for a batch."""


@contextmanager
def joined(requested_device: str) -> Iterator[tuple[RankInfo, torch.device]]:
    """This process's rank and device for the length of a run: joins torchrun's process group (when launched
    with several processes) and leaves it afterwards, also on error. A run that ends normally first waits at a
    barrier for every rank (:func:`~dp5k_learn.distributed.teardown`)."""
    info, device = D.setup(requested_device)
    ok = False
    try:
        yield info, device
        ok = True
    finally:
        D.teardown(info if ok else None)


def open_splits(root: Path, data: DataConfig, seed: int) -> tuple[DPPairDataset, DPPairDataset]:
    """The training set (``data``'s random crops, ``data.samples_per_epoch`` items per epoch) and the validation
    set (whole val pairs; the train pairs when val is empty, with a warning).

    Raises:
        EmptySplitError: the train split is empty.
    """
    crop = CropSpec(data.crop_px, data.min_valid_fraction, vflip=data.vflip)
    try:
        train_ds = DPPairDataset(root, "train", crop, seed=seed, length=data.samples_per_epoch)
    except EmptySplitError as exc:
        raise EmptySplitError("the train split is empty; nothing to train on", where=root / "dataset.json") from exc
    try:
        val_ds = DPPairDataset(root, "val", CropSpec(), seed=seed)
    except EmptySplitError:
        logger.warning("%s: empty val split; selecting the checkpoint on the train split", root)
        val_ds = DPPairDataset(root, "train", CropSpec(), seed=seed)
    return train_ds, val_ds


def optimiser_step(module: nn.Module, opt: torch.optim.Optimizer, sched: torch.optim.lr_scheduler.LRScheduler,
                   batch: DPBatch, forward: Forward, loss: Loss, *, grad_clip: float, amp: bool = False, step: int = 0,
                   where: str = "train") -> Tensor:
    """One optimiser step, the same for every trainer: ``forward`` (under bfloat16 autocast when ``amp``),
    ``loss``, backward, clipping of the global gradient norm of ``module``'s parameters to ``grad_clip``
    (0 = off), the optimiser and the schedule.

    Args:
        module: the network itself (not its DistributedDataParallel wrapper, which ``forward`` may run).
        step: the step's index (for the error message). where: names the run in the error message.

    Returns:
        The loss (detached scalar).

    Raises:
        StageError: the loss is not finite.
    """
    with torch.autocast(device_type=batch.sharp.device.type, dtype=torch.bfloat16, enabled=amp):
        output = forward(batch)
    value = loss(output, batch)
    if not torch.isfinite(value):
        raise StageError(f"loss is {float(value.detach())} at step {step} (lower the learning rate?)", where=where)
    opt.zero_grad(set_to_none=True)
    value.backward()
    if grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(module.parameters(), grad_clip)
    opt.step()
    sched.step()
    return value.detach()


@dataclass
class TrainingRun:
    """One training run's parts (:func:`build_run`).

    Attributes:
        module: the network (checkpointed; its parameters are clipped).
        net: what runs the forward pass: ``module``, or its DistributedDataParallel wrapper under torchrun.
        opt, sched: Adam and its per-step cosine schedule (``sched.T_max`` = epochs x steps per epoch).
        train_ds, sampler, loader: the training set, its DistributedSampler and the DataLoader over both.
        rank, device: where this process sits and computes.
        amp: bfloat16 autocast (CUDA only).
        grad_clip: the global gradient-norm clip (0 = off).
        epochs, seed: the run's length and seed.
    """

    module: nn.Module
    net: nn.Module
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.CosineAnnealingLR
    train_ds: DPPairDataset
    sampler: DistributedSampler
    loader: DataLoader
    rank: RankInfo
    device: torch.device
    amp: bool
    grad_clip: float
    epochs: int
    seed: int

    def step(self, batch: DPBatch, k: int, forward: Forward, loss: Loss, where: str = "train") -> Tensor:
        """:func:`optimiser_step` with this run's optimiser, schedule, clipping and AMP setting."""
        return optimiser_step(self.module, self.opt, self.sched, batch, forward, loss, grad_clip=self.grad_clip,
                              amp=self.amp, step=k, where=where)


def build_run(module: nn.Module, train_ds: DPPairDataset, data: DataConfig, optim: OptimConfig, seed: int,
              rank: RankInfo, device: torch.device) -> TrainingRun:
    """Adam (betas 0.9, 0.999) on ``module``'s parameters, a DistributedSampler (shuffled by ``seed``) and
    DataLoader of ``data.batch_size`` items per process, cosine annealing from ``optim.lr`` to ``optim.lr_min``
    over every step of ``optim.epochs`` epochs, the DistributedDataParallel wrapper under torchrun, and AMP
    where ``optim.amp`` and the device is CUDA. ``module`` must already be on ``device``."""
    opt = torch.optim.Adam(module.parameters(), lr=optim.lr, betas=(0.9, 0.999))
    sampler = DistributedSampler(train_ds, num_replicas=rank.world_size, rank=rank.rank, shuffle=True, seed=seed,
                                 drop_last=False)
    loader = DataLoader(train_ds, batch_size=data.batch_size, sampler=sampler, num_workers=data.num_workers,
                        collate_fn=collate_dp)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, optim.epochs * len(loader)), eta_min=optim.lr_min)
    net = module
    if rank.enabled:
        net = DistributedDataParallel(module, device_ids=[device.index] if device.type == "cuda" else None)
    return TrainingRun(module=module, net=net, opt=opt, sched=sched, train_ds=train_ds, sampler=sampler, loader=loader,
                       rank=rank, device=device, amp=optim.amp and device.type == "cuda", grad_clip=optim.grad_clip,
                       epochs=optim.epochs, seed=seed)


@torch.no_grad()
def validate_pairs(model: nn.Module, ds: DPPairDataset, score: Score, rank: RankInfo, device: torch.device,
                   max_pairs: int = 0) -> dict[str, float]:
    """Mean ``score`` (SSIM / PSNR / MAE) over whole pairs of ``ds`` (at most ``max_pairs``; 0 = all), ``model`` in
    eval mode. Pairs are sharded over processes without padding; sums and counts are all-reduced, so every process
    gets the same numbers."""
    was_training = model.training
    model.eval()
    n = len(ds.ids) if max_pairs <= 0 else min(max_pairs, len(ds.ids))
    acc = torch.zeros(4, dtype=torch.float64, device=device)
    for i in range(rank.rank, n, rank.world_size):
        m = score(collate_dp([ds[i]]).to(device))
        acc += torch.tensor([float(m["ssim"][0]), float(m["psnr"][0]), float(m["mae"][0]), 1.0], dtype=torch.float64,
                            device=device)
    acc = D.all_reduce_sum(acc, rank)
    model.train(was_training)
    count = max(float(acc[3]), 1.0)
    return {"ssim": float(acc[0]) / count, "psnr": float(acc[1]) / count, "mae": float(acc[2]) / count}


def finetune(module: nn.Module, dataset: str | os.PathLike[str], cfg: FinetuneConfig, forward: Forward, loss: Loss, *,
             device: torch.device | str = "cpu", is_new: Callable[[str], bool] = lambda name: False,
             desc: str = "fine-tune") -> list[float]:
    """Fine-tune ``module`` in place on ``dataset``'s train crops for exactly ``cfg.steps`` :func:`optimiser_step`
    calls, with no epochs, validation or checkpoints.

    The crops and their order depend only on ``cfg.seed`` (and the dataset), so two calls with the same settings
    see identical batches (a control and an extension are trained on the same data). Adam with cosine annealing
    from ``cfg.lr`` to 0; the parameters whose names ``is_new`` accepts (ones a structural extension added) at
    ``cfg.new_lr_mult`` times that.

    Returns:
        The loss of every step (length ``cfg.steps``); ``module`` is left in eval mode.

    Raises:
        EmptySplitError: the train split is empty.
        StageError: the loss became NaN.
    """
    device = torch.device(device)
    ds = DPPairDataset(dataset, "train", CropSpec(cfg.crop_px, vflip=False), seed=cfg.seed, length=max(1, cfg.steps * cfg.batch_size))
    order = np.random.default_rng(cfg.seed).permutation(len(ds))
    module.to(device)
    new = [p for n, p in module.named_parameters() if is_new(n)]
    old = [p for n, p in module.named_parameters() if not is_new(n)]
    groups = [{"params": old, "lr": cfg.lr}] + ([{"params": new, "lr": cfg.lr * cfg.new_lr_mult}] if new else [])
    opt = torch.optim.Adam(groups, lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, cfg.steps), eta_min=0.0)
    module.train()
    losses: list[float] = []
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):  # dropout from cfg.seed only
        torch.manual_seed(cfg.seed)
        for k in progress(range(cfg.steps), desc=desc, unit="step"):
            idx = order[(k * cfg.batch_size) % len(ds) :][: cfg.batch_size]
            batch = collate_dp([ds[int(i)] for i in idx]).to(device)
            losses.append(float(optimiser_step(module, opt, sched, batch, forward, loss, grad_clip=cfg.grad_clip, step=k,
                                               where="fine-tune")))
    module.eval()
    return losses
