"""The epoch loop every trained network of dp5k shares: resume, steps, validation, best/last checkpoints, history.

``dp5k train`` (the Neural DP Simulator, :mod:`neural_dp.train`) and ``dp5k deblur train`` (the DP deblurring
network, :mod:`dp5k_deblur.train`) both run :func:`run_epochs`; only what one optimiser step and one validation
do differs, and the caller passes those in. It writes into ``out``:

* ``config.json``: the resolved configuration;
* ``last.pt``: everything needed to resume, rewritten atomically after every epoch;
* ``best.pt``: the weights with the highest validation SSIM so far;
* ``history.json``: per-epoch loss, validation metrics, learning rate and throughput.

The data and dropout of every epoch are seeded by ``(seed, epoch, rank)``, so a resumed run reproduces an
uninterrupted one. Checkpoint layout: :mod:`neural_dp.checkpoint`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader, DistributedSampler

from dp5k_common.errors import BadInputError
from dp5k_common.io import write_json_atomic
from dp5k_common.progress import progress

from . import distributed as D
from .checkpoint import load_checkpoint, save_checkpoint
from .data import DPPairDataset

logger = logging.getLogger(__name__)


@dataclass
class TrainResult:
    """What a run produced."""

    out_dir: Path
    best_val_ssim: float
    best_epoch: int
    epochs_done: int
    steps: int
    history: list[dict[str, float]] = field(default_factory=list)


@dataclass
class EpochLoop:
    """One training run's parts, built by the caller.

    Attributes:
        module: the network whose ``state_dict`` is checkpointed (not its DDP wrapper).
        opt, sched: Adam and its per-step schedule (``sched.T_max`` is reset to ``epochs * len(loader)``).
        train_ds: the training dataset (its ``set_epoch`` selects each epoch's crops).
        loader, sampler: the DataLoader over ``train_ds`` and its DistributedSampler.
        step: ``step(batch, step_index) -> loss`` runs one optimiser step on a batch already on the device.
        validate: ``validate() -> {"ssim", "psnr", "mae"}``, the same numbers on every process.
        model_config: the network's config as a dict (a resume refuses a different one).
        config: the whole run's config as a dict (stored in each checkpoint).
        epochs: total epochs of the run.
        seed: the run's seed.
        defaults: ``model_config`` keys added since older checkpoints were written, at their defaults.
    """

    module: torch.nn.Module
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.CosineAnnealingLR
    train_ds: DPPairDataset
    loader: DataLoader
    sampler: DistributedSampler
    step: Callable[[Any, int], torch.Tensor]
    validate: Callable[[], dict[str, float]]
    model_config: dict[str, Any]
    config: dict[str, Any]
    epochs: int
    seed: int
    defaults: dict[str, Any] = field(default_factory=dict)


def run_epochs(loop: EpochLoop, out: Path, info: D.DistInfo, *, resume: bool, on_fresh_start: Callable[[], None] | None = None,
               on_epoch_end: Callable[[int, dict[str, float]], None] | None = None, desc: str = "train") -> TrainResult:
    """Train ``loop.module`` for ``loop.epochs`` epochs (or resume from ``out/last.pt``), checkpointing every epoch.

    Args:
        on_fresh_start: called once when no checkpoint is resumed (data-driven initialisation).
        on_epoch_end: called as ``on_epoch_end(epoch, record)`` after each epoch's checkpoint is written.

    Raises:
        BadInputError: ``last.pt`` was written with another model config.
    """
    device = info.device
    steps_per_epoch = len(loop.loader)
    loop.sched.T_max = max(1, loop.epochs * steps_per_epoch)
    start_epoch, step = 0, 0
    best_ssim, best_epoch = -math.inf, -1
    history: list[dict[str, float]] = []
    last_path, best_path = out / "last.pt", out / "best.pt"
    if resume and last_path.is_file():
        state = load_checkpoint(last_path, map_location=device)
        saved_model = state.get("model_config")
        if isinstance(saved_model, dict):  # keys added to the config since (at their defaults) do not block a resume
            saved_model = {**loop.defaults, **saved_model}
        if saved_model != loop.model_config:
            raise BadInputError("the checkpoint's model config differs from this run's; use another --out or the same config",
                                where=last_path)
        loop.module.load_state_dict(state["model"])
        loop.opt.load_state_dict(state["optim"])
        loop.sched.load_state_dict(state["sched"])
        loop.sched.T_max = max(1, loop.epochs * steps_per_epoch)  # a resumed run may extend the schedule (more epochs)
        start_epoch, step = int(state["epoch"]), int(state["step"])
        best_ssim, best_epoch = float(state["best_val_ssim"]), int(state["best_epoch"])
        history = list(state.get("history", []))
        if info.is_main:
            logger.info("resuming from %s at epoch %d (step %d)", last_path, start_epoch, step)
    elif on_fresh_start is not None:
        on_fresh_start()
    if info.is_main:
        write_json_atomic(out / "config.json", loop.config)

    bar = progress(total=loop.epochs * steps_per_epoch, initial=step, desc=desc, unit="step") if info.is_main else None
    try:
        for epoch in range(start_epoch, loop.epochs):
            loop.train_ds.set_epoch(epoch)
            loop.sampler.set_epoch(epoch)
            torch.manual_seed(loop.seed * 1_000_003 + epoch * 7919 + info.rank)
            loop.module.train()
            t0 = time.perf_counter()
            loss_sum = torch.zeros(2, dtype=torch.float64, device=device)
            samples = 0
            for batch in loop.loader:
                batch = batch.to(device)
                n = batch.sharp.shape[0]
                loss = float(loop.step(batch, step))
                step += 1
                samples += n
                loss_sum += torch.tensor([loss * n, n], dtype=torch.float64, device=device)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(epoch=epoch + 1, loss=f"{loss:.4f}", best_ssim=f"{max(best_ssim, 0):.4f}")
            loss_sum = D.all_reduce_sum(loss_sum, info)
            elapsed = time.perf_counter() - t0
            val = loop.validate()
            record = {
                "epoch": epoch + 1, "step": step, "loss": float(loss_sum[0] / loss_sum[1].clamp_min(1)),
                "val_ssim": val["ssim"], "val_psnr": val["psnr"], "val_mae": val["mae"],
                "lr": float(loop.sched.get_last_lr()[0]),
                "train_samples_per_s": float(samples * info.world_size / max(elapsed, 1e-9)),
            }
            history.append(record)
            improved = val["ssim"] > best_ssim
            if improved:
                best_ssim, best_epoch = val["ssim"], epoch + 1
            state = {
                "model": loop.module.state_dict(), "model_config": loop.model_config, "config": loop.config,
                "optim": loop.opt.state_dict(), "sched": loop.sched.state_dict(), "epoch": epoch + 1, "step": step,
                "best_val_ssim": float(best_ssim), "best_epoch": int(best_epoch), "history": history,
            }
            if info.is_main:
                if improved:
                    save_checkpoint(best_path, state)
                save_checkpoint(last_path, state)
                write_json_atomic(out / "history.json", history)
                logger.info("epoch %d: loss %.5f, val SSIM %.4f, PSNR %.2f dB%s", epoch + 1, record["loss"],
                            val["ssim"], val["psnr"], " (best)" if improved else "")
            D.barrier(info)
            if on_epoch_end is not None:
                on_epoch_end(epoch + 1, record)
    finally:
        if bar is not None:
            bar.close()
    return TrainResult(out, float(best_ssim), int(best_epoch), len(history), step, history)
