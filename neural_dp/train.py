"""Train the Neural DP Simulator (Sec. 5.1): Eq. (8)/(9) loss, Adam + cosine annealing, best-by-val-SSIM.

One function, :func:`train`, runs in a single process (CPU by default, CUDA when present) or as one of
many processes under ``torchrun`` (DistributedDataParallel; see :mod:`neural_dp.distributed`). It writes
into ``out_dir``:

* ``config.json``: the resolved configuration;
* ``last.pt``: everything needed to resume, rewritten atomically after every epoch;
* ``best.pt``: the weights with the highest validation masked SSIM so far (what ``dp5k evaluate`` uses);
* ``history.json``: per-epoch loss, validation metrics, learning rate and throughput.

Running the same command again resumes from ``last.pt`` (epoch granularity; the data and dropout of
every epoch are seeded by ``(seed, epoch, rank)``, so a resumed run reproduces an uninterrupted one).

Every optimiser step, in training and in :func:`finetune` (an existing simulator trained for a fixed number of
steps, without epochs or checkpoints, :class:`~neural_dp.config.FinetuneConfig`), is :func:`train_step`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, DistributedSampler

from dp5k_common.errors import EmptySplitError, StageError
from dp5k_common.progress import progress

from . import distributed as D
from .batch import DPBatch
from .config import FinetuneConfig, TrainConfig
from .epochs import EpochLoop, TrainResult, run_epochs
from .data import CropSpec, DPPairDataset, collate_dp
from .losses import dp_loss
from .metrics import view_metrics
from .model import ModelConfig
from .simulators.neural import NeuralDPSimulator, model_inputs

logger = logging.getLogger(__name__)


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


@torch.no_grad()
def validate(sim: NeuralDPSimulator, ds: DPPairDataset, info: D.DistInfo, max_pairs: int = 0) -> dict[str, float]:
    """Masked SSIM / PSNR / MAE (mean of L and R, mean over pairs) on full-resolution pairs.

    Pairs are sharded over processes without padding; sums and counts are all-reduced, so every process
    gets the same numbers.
    """
    was_training = sim.training
    sim.eval()
    n = len(ds.ids) if max_pairs <= 0 else min(max_pairs, len(ds.ids))
    acc = torch.zeros(4, dtype=torch.float64, device=info.device)
    for i in range(info.rank, n, info.world_size):
        batch = collate_dp([ds[i]]).to(info.device)
        left, right = sim(batch)
        m = view_metrics(left.float(), right.float(), batch.left, batch.right, batch.valid)
        acc += torch.tensor([float(m["ssim"][0]), float(m["psnr"][0]), float(m["mae"][0]), 1.0],
                            dtype=torch.float64, device=info.device)
    acc = D.all_reduce_sum(acc, info)
    sim.train(was_training)
    count = max(float(acc[3]), 1.0)
    return {"ssim": float(acc[0]) / count, "psnr": float(acc[1]) / count, "mae": float(acc[2]) / count}


def train_step(net: torch.nn.Module, module: torch.nn.Module, batch: DPBatch, opt: torch.optim.Optimizer,
               sched: torch.optim.lr_scheduler.LRScheduler, *, coc_scale_px: float, border_px: int, grad_weight: float,
               grad_clip: float, amp: bool = False, step: int = 0, where: str = "train") -> torch.Tensor:
    """One optimiser step of the Neural DP Simulator: forward, the loss of Eq. (8) on the valid mask minus a
    ``border_px`` frame, backward, global gradient clipping, Adam and the schedule. ``dp5k train`` and
    :func:`finetune` both run it.

    Args:
        net: what runs the forward pass (the network, or its DistributedDataParallel wrapper).
        module: the network itself (its parameters are clipped).
        batch: a training batch on the network's device.
        coc_scale_px: the model's CoC input scale (``ModelConfig.coc_scale_px``).
        amp: bfloat16 autocast (CUDA only).
        step: the step's index (for the error message).

    Returns:
        The loss (detached scalar).

    Raises:
        StageError: the loss is not finite.
    """
    inputs = model_inputs(batch, coc_scale_px)
    with torch.autocast(device_type=batch.sharp.device.type, dtype=torch.bfloat16, enabled=amp):
        left, right = net(batch.sharp, inputs)
    loss = dp_loss(left.float(), right.float(), batch.left, batch.right, loss_mask(batch.valid, border_px), grad_weight)
    if not torch.isfinite(loss):
        raise StageError(f"loss is {float(loss)} at step {step} (lower the learning rate?)", where=where)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(module.parameters(), grad_clip)
    opt.step()
    sched.step()
    return loss.detach()


NEW_PARAMETER_PREFIX = "scale_head."
"""Parameters a structural extension adds to a trained network (:func:`neural_dp.model.extend_multiscale`);
:func:`finetune` trains them at ``FinetuneConfig.new_lr_mult`` times the rate."""


def finetune(sim: NeuralDPSimulator, dataset: str | os.PathLike[str], cfg: FinetuneConfig, device: torch.device | str = "cpu",
             desc: str = "fine-tune") -> list[float]:
    """Fine-tune a simulator in place on ``dataset``'s train crops for exactly ``cfg.steps`` steps of
    :func:`train_step`, with no epochs, validation or checkpoints.

    The crops and their order depend only on ``cfg.seed`` (and the dataset), so two calls with the same settings
    see identical batches (a control and an extension are trained on the same data). Adam with cosine
    annealing from ``cfg.lr`` to 0; parameters named ``scale_head.*`` at ``cfg.new_lr_mult`` times that.

    Returns:
        The loss of every step (length ``cfg.steps``); ``sim`` is left in eval mode.

    Raises:
        EmptySplitError: the train split is empty.
        StageError: the loss became NaN.
    """
    device = torch.device(device)
    ds = DPPairDataset(dataset, "train", CropSpec(cfg.crop_px, vflip=False), seed=cfg.seed, length=max(1, cfg.steps * cfg.batch_size))
    order = np.random.default_rng(cfg.seed).permutation(len(ds))
    border = sim.net.reach_px if cfg.border_px is None else int(cfg.border_px)
    sim.to(device)
    new = [p for n, p in sim.net.named_parameters() if n.startswith(NEW_PARAMETER_PREFIX)]
    old = [p for n, p in sim.net.named_parameters() if not n.startswith(NEW_PARAMETER_PREFIX)]
    groups = [{"params": old, "lr": cfg.lr}] + ([{"params": new, "lr": cfg.lr * cfg.new_lr_mult}] if new else [])
    opt = torch.optim.Adam(groups, lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, cfg.steps), eta_min=0.0)
    torch.manual_seed(cfg.seed)
    sim.train()
    losses: list[float] = []
    for k in progress(range(cfg.steps), desc=desc, unit="step"):
        idx = order[(k * cfg.batch_size) % len(ds) :][: cfg.batch_size]
        batch = collate_dp([ds[int(i)] for i in idx]).to(device)
        loss = train_step(sim.net, sim.net, batch, opt, sched, coc_scale_px=sim.cfg.coc_scale_px, border_px=border,
                          grad_weight=cfg.grad_weight, grad_clip=cfg.grad_clip, step=k, where="fine-tune")
        losses.append(float(loss))
    sim.eval()
    return losses


def _seed_all(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % (2**32))


def _open(root: Path, split: str, crop: CropSpec, seed: int, length: int = 0) -> DPPairDataset | None:
    try:
        return DPPairDataset(root, split, crop, seed=seed, length=length)
    except EmptySplitError:
        return None


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
    info = D.setup(cfg.device)
    try:
        return _train(Path(dataset), Path(out_dir), cfg, info, resume, on_epoch_end)
    finally:
        D.teardown()


def _train(root: Path, out: Path, cfg: TrainConfig, info: D.DistInfo, resume: bool,
           on_epoch_end: Callable[[int, dict[str, float]], None] | None) -> TrainResult:
    device = info.device
    out.mkdir(parents=True, exist_ok=True)
    crop = CropSpec(cfg.data.crop_px, cfg.data.min_valid_fraction, vflip=cfg.data.vflip)
    train_ds = _open(root, "train", crop, cfg.seed, cfg.data.samples_per_epoch)
    if train_ds is None:
        raise EmptySplitError("the train split is empty; nothing to train on", where=root / "dataset.json")
    val_ds = _open(root, "val", CropSpec(), cfg.seed)
    if val_ds is None:
        logger.warning("%s: empty val split; selecting the checkpoint on the train split", root)
        val_ds = DPPairDataset(root, "train", CropSpec(), seed=cfg.seed)

    _seed_all(cfg.seed)
    sim = NeuralDPSimulator(cfg.model).to(device)
    opt = torch.optim.Adam(sim.net.parameters(), lr=cfg.optim.lr, betas=(0.9, 0.999))
    sampler = DistributedSampler(train_ds, num_replicas=info.world_size, rank=info.rank, shuffle=True,
                                 seed=cfg.seed, drop_last=False)
    loader = DataLoader(train_ds, batch_size=cfg.data.batch_size, sampler=sampler, num_workers=cfg.data.num_workers,
                        collate_fn=collate_dp)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, cfg.optim.epochs * len(loader)), eta_min=cfg.optim.lr_min)
    net: torch.nn.Module = sim.net
    if info.enabled:
        net = DistributedDataParallel(sim.net, device_ids=[device.index] if device.type == "cuda" else None)
    border = sim.net.reach_px  # K // 2, more with multi-scale kernels
    use_amp = cfg.optim.amp and device.type == "cuda"

    def step(batch: DPBatch, k: int) -> torch.Tensor:
        return train_step(net, sim.net, batch, opt, sched, coc_scale_px=cfg.model.coc_scale_px, border_px=border,
                          grad_weight=cfg.optim.grad_weight, grad_clip=cfg.optim.grad_clip, amp=use_amp, step=k)

    loop = EpochLoop(module=sim.net, opt=opt, sched=sched, train_ds=train_ds, loader=loader, sampler=sampler, step=step,
                     validate=lambda: validate(sim, val_ds, info, cfg.data.val_pairs), model_config=asdict(cfg.model),
                     config=cfg.to_dict(), epochs=cfg.optim.epochs, seed=cfg.seed, defaults=asdict(ModelConfig()))
    return run_epochs(loop, out, info, resume=resume, on_fresh_start=lambda: init_view_gain(sim, train_ds),
                      on_epoch_end=on_epoch_end)
