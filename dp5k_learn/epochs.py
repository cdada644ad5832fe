"""The epoch loop every trained network of dp5k shares: resume, steps, validation, best/last checkpoints, history.

``dp5k train`` (the Neural DP Simulator, ``neural_dp.train``) and ``dp5k deblur train`` (the DP deblurring
network, ``dp5k_deblur.train``) both run :func:`run_epochs` over a :class:`~dp5k_learn.training.TrainingRun`;
only their network's forward pass, loss and validation score differ, and the caller passes those in. It writes
into ``out``:

* ``config.json``: the resolved configuration;
* ``last.pt``: everything needed to resume, rewritten atomically after every epoch;
* ``best.pt``: the weights with the highest validation SSIM so far;
* ``history.json``: per-epoch loss, validation metrics, learning rate and throughput.

The data and dropout of every epoch are seeded by ``(seed, epoch, rank)``, so a resumed run reproduces an
uninterrupted one. Checkpoint layout: :mod:`dp5k_learn.checkpoint`.
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

from dp5k_common.errors import BadInputError
from dp5k_common.io import write_json_atomic
from dp5k_common.progress import progress

from . import distributed as D
from .checkpoint import load_checkpoint, save_checkpoint
from .training import Forward, Loss, TrainingRun

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
    report: dict[str, Any] = field(default_factory=dict)
    """What the trainer adds about the run (``neural_dp``: the choice between network and physical model)."""


@dataclass
class EpochLoop:
    """What the caller's network adds to a :class:`~dp5k_learn.training.TrainingRun`.

    Attributes:
        run: the run's parts (:func:`~dp5k_learn.training.build_run`); ``run.sched.T_max`` is reset to
            ``epochs * len(loader)``, and ``run.train_ds.set_epoch`` selects each epoch's crops.
        forward, loss: the network's forward pass and training loss (:func:`~dp5k_learn.training.optimiser_step`).
        validate: ``validate() -> {"ssim", "psnr", "mae"}``, the same numbers on every process.
        model_config: the network's config as a dict (a resume refuses a different one).
        config: the whole run's config as a dict (stored in each checkpoint).
        defaults: ``model_config`` keys added since older checkpoints were written, at their defaults.
        patience: stop once this many epochs in a row brought no better validation score (0 = run every epoch).
        best_name: the file the best weights go to (``best.pt``; a trainer that chooses afterwards between them
            and something else writes ``best.pt`` itself).
        select: the validation metric that picks the best epoch and drives early stopping: ``"ssim"`` (the paper's)
            or ``"psnr"``.
    """

    run: TrainingRun
    forward: Forward
    loss: Loss
    validate: Callable[[], dict[str, float]]
    model_config: dict[str, Any]
    config: dict[str, Any]
    defaults: dict[str, Any] = field(default_factory=dict)
    patience: int = 0
    best_name: str = "best.pt"
    select: str = "ssim"


def run_epochs(loop: EpochLoop, out: Path, *, resume: bool, on_fresh_start: Callable[[], None] | None = None,
               on_epoch_end: Callable[[int, dict[str, float]], None] | None = None, desc: str = "train") -> TrainResult:
    """Train ``loop.run.module`` for ``loop.run.epochs`` epochs (or resume from ``out/last.pt``), checkpointing every
    epoch.

    Args:
        on_fresh_start: called once when no checkpoint is resumed (data-driven initialisation).
        on_epoch_end: called as ``on_epoch_end(epoch, record)`` after each epoch's checkpoint is written.

    Raises:
        BadInputError: ``last.pt`` was written with another model config.
    """
    run = loop.run
    info, device = run.rank, run.device
    steps_per_epoch = len(run.loader)
    run.sched.T_max = max(1, run.epochs * steps_per_epoch)
    start_epoch, step = 0, 0
    if loop.select not in ("ssim", "psnr"):
        raise BadInputError(f"the validation metric must be ssim or psnr, got {loop.select!r}", where="config")
    best_ssim, best_score, best_epoch = -math.inf, -math.inf, -1
    history: list[dict[str, float]] = []
    last_path, best_path = out / "last.pt", out / loop.best_name
    if resume and last_path.is_file():
        state = load_checkpoint(last_path, map_location=device)
        saved_model = state.get("model_config")
        if isinstance(saved_model, dict):  # keys added to the config since (at their defaults) do not block a resume
            saved_model = {**loop.defaults, **saved_model}
        if saved_model != loop.model_config:
            raise BadInputError("the checkpoint's model config differs from this run's; use another --out or the same config",
                                where=last_path)
        run.module.load_state_dict(state["model"])
        run.opt.load_state_dict(state["optim"])
        run.sched.load_state_dict(state["sched"])
        run.sched.T_max = max(1, run.epochs * steps_per_epoch)  # a resumed run may extend the schedule (more epochs)
        start_epoch, step = int(state["epoch"]), int(state["step"])
        best_ssim, best_epoch = float(state["best_val_ssim"]), int(state["best_epoch"])
        best_score = float(state.get("best_val_score", best_ssim))
        history = list(state.get("history", []))
        if info.is_main:
            logger.info("resuming from %s at epoch %d (step %d)", last_path, start_epoch, step)
    elif on_fresh_start is not None:
        on_fresh_start()
    if info.is_main:
        write_json_atomic(out / "config.json", loop.config)

    bar = progress(total=run.epochs * steps_per_epoch, initial=step, desc=desc, unit="step") if info.is_main else None
    try:
        for epoch in range(start_epoch, run.epochs):
            if loop.patience > 0 and best_epoch > 0 and epoch - best_epoch >= loop.patience:
                if info.is_main:
                    logger.info("stopping after epoch %d: no better validation %s for %d epochs (best: epoch %d)",
                                epoch, loop.select.upper(), loop.patience, best_epoch)
                break
            run.train_ds.set_epoch(epoch)
            run.sampler.set_epoch(epoch)
            run.module.train()
            # dropout draws from (seed, epoch, rank) only, on a forked generator: the caller's global state is left as it was
            with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
                torch.manual_seed(run.seed * 1_000_003 + epoch * 7919 + info.rank)
                t0 = time.perf_counter()
                loss_sum = torch.zeros(2, dtype=torch.float64, device=device)
                samples = 0
                for batch in run.loader:
                    batch = batch.to(device)
                    n = batch.sharp.shape[0]
                    loss = float(run.step(batch, step, loop.forward, loop.loss))
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
                "lr": float(run.sched.get_last_lr()[0]),
                "train_samples_per_s": float(samples * info.world_size / max(elapsed, 1e-9)),
            }
            history.append(record)
            improved = val[loop.select] > best_score
            if improved:
                best_score, best_ssim, best_epoch = val[loop.select], val["ssim"], epoch + 1
            state = {
                "model": run.module.state_dict(), "model_config": loop.model_config, "config": loop.config,
                "optim": run.opt.state_dict(), "sched": run.sched.state_dict(), "epoch": epoch + 1, "step": step,
                "best_val_ssim": float(best_ssim), "best_epoch": int(best_epoch), "history": history,
                "best_val_score": float(best_score), "select": loop.select,
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
