"""Train the Neural DP Simulator (Sec. 5.1): Eq. (8)/(9) loss, Adam + cosine annealing, best-by-val-SSIM.

**What ``dp5k train`` does by default** (``model.prior = "physical"``, :func:`train`):

1. hold out validation pairs that the network never trains on (:mod:`neural_dp.holdout`: the val split, else whole
   train photos, else spatially separate tiles of the one photo), with a warning when the train set is a few photos;
   refuse (exit 3, nothing written) a train split without valid depth or a single pair with nothing to hold out;
2. fit the physical model (``physics.simulator``: the base model, or a diagnosed one) on the train crops exactly as
   ``dp5k evaluate`` fits ``base``, and score it on the validation pairs;
3. optionally pre-train on calibrated renders (:mod:`neural_dp.pretrain`, ``pretrain.simulator``);
4. train the physics-first network (:mod:`neural_dp.model`: it starts as that physical model, bit for bit) on the
   train pairs with DP-geometry augmentations (:mod:`neural_dp.augment`), validating every epoch and stopping early
   (``select.patience``); its best weights by validation PSNR (``select.metric``) go to ``network.pt``;
5. **keep the better** (``select.keep``): ``best.pt`` is the network only if it beats the physical model on the
   validation pairs (PSNR gain with a 95 % bootstrap interval above 0, SSIM not lower); otherwise ``best.pt`` is
   the network at its physics-equal initialisation, which ``--simulator neural:RUN/best.pt`` renders exactly as
   the physical model. ``report.json`` holds both scores, the difference, the decision and a sentence saying why;
   the command prints the sentence.

``model.prior = "none"`` is the paper's network and training as released (val split, else the train split; vertical
flips; best checkpoint by val SSIM), optionally after calibrated pre-training.

This module holds only what is the Neural DP Simulator's own: its forward pass (:func:`forward_fn`), its loss
(Eq. (8) on the valid mask minus the kernels' reach, :func:`loss_fn`), its validation score and the data-driven
initialisation of its view gains. The run's set-up (Adam, schedule, sampler, loader, DDP, AMP), the optimiser
step and the epoch loop are :mod:`dp5k_learn`'s, shared with ``dp5k deblur train``.

:func:`train` runs in a single process (CPU by default, CUDA when present) or as one of many processes under
``torchrun`` (DistributedDataParallel; see :mod:`dp5k_learn.distributed`). It writes into ``out_dir``:

* ``config.json``: the resolved configuration;
* ``last.pt``: everything needed to resume, rewritten atomically after every epoch;
* ``best.pt``: the weights with the highest validation masked SSIM so far (what ``dp5k evaluate`` uses);
* ``history.json``: per-epoch loss, validation metrics, learning rate and throughput;
* with a physical prior also ``network.pt`` (the network's best weights) and ``report.json`` (the decision).

Running the same command again resumes from ``last.pt`` (epoch granularity; the data and dropout of
every epoch are seeded by ``(seed, epoch, rank)``, so a resumed run reproduces an uninterrupted one). Seeds reach
every draw as generators (``np.random.default_rng``, a forked torch generator): training leaves the process's
global random state as it found it.

:func:`finetune` trains an existing simulator for a fixed number of steps, without epochs or checkpoints
(:class:`~dp5k_learn.config.FinetuneConfig`), with the same step.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from dp5k_common.dataset import DatasetReader
from dp5k_common.errors import BadInputError
from dp5k_common.io import write_json_atomic
from dp5k_common.sharding import RankInfo
from dp5k_learn import distributed as D
from dp5k_learn import training
from dp5k_learn.batch import DPBatch
from dp5k_learn.checkpoint import load_checkpoint, save_checkpoint
from dp5k_learn.config import FinetuneConfig
from dp5k_learn.data import CropSpec, DPPairDataset, collate_dp
from dp5k_learn.epochs import EpochLoop, TrainResult, run_epochs
from dp5k_learn.intervals import Resampler
from dp5k_learn.losses import dp_loss
from dp5k_learn.metrics import view_metrics
from dp5k_learn.training import Forward, Loss

from .augment import PhysicalPairs
from .config import TrainConfig
from .evaluate import _fit_batches
from .holdout import Holdout, plan_holdout
from .model import ModelConfig
from .simulators.base import BaseModel
from .simulators.base.spec import model_to_spec
from .simulators.catalog import SimulatorSpec
from .simulators.neural import NeuralDPSimulator, build_prior, model_inputs

logger = logging.getLogger(__name__)

NETWORK_CKPT = "network.pt"
"""The physics-first network's best weights (by ``select.metric``); ``best.pt`` is these or the physical model."""
REPORT = "report.json"
MIN_CLUSTERS = 3
"""Fewer validation scenes than this are too few to resample: the decision's bootstrap then resamples pairs."""


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


def forward_fn(net: nn.Module, coc_scale_px: float, sim: NeuralDPSimulator | None = None) -> Forward:
    """The network's forward pass on a batch: ``(left, right)`` from the sharp image and its input (:func:`model_inputs`,
    or ``sim.inputs``, which adds the physical views, for a physical-prior network). ``net`` is the network or its
    DistributedDataParallel wrapper."""
    if sim is not None and sim.physical:
        return lambda batch: net(batch.sharp, sim.inputs(batch))
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
    losses = training.finetune(sim.net, dataset, cfg, forward_fn(sim.net, sim.cfg.coc_scale_px, sim),
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
    if cfg.model.prior == "physical":
        holdout = plan_holdout(dataset, cfg.select.holdout, cfg.seed)  # refuses unusable data before anything is written
        with training.joined(cfg.device) as (info, device):
            return _train_physical(Path(dataset), Path(out_dir), cfg, holdout, info, device, resume, on_epoch_end)
    with training.joined(cfg.device) as (info, device):
        return _train(Path(dataset), Path(out_dir), cfg, info, device, resume, on_epoch_end)


def new_simulator(cfg: ModelConfig, seed: int, device: torch.device) -> NeuralDPSimulator:
    """A freshly initialised simulator, its weights drawn from ``seed`` alone (a forked generator: the global one
    is left as it was)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return NeuralDPSimulator(cfg).to(device)


def _train(root: Path, out: Path, cfg: TrainConfig, info: RankInfo, device: torch.device, resume: bool,
           on_epoch_end: Callable[[int, dict[str, float]], None] | None) -> TrainResult:
    """The paper's network and training (``model.prior = "none"``)."""
    out.mkdir(parents=True, exist_ok=True)
    train_ds, val_ds = training.open_splits(root, cfg.data, cfg.seed)
    sim = new_simulator(cfg.model, cfg.seed, device)
    init = None
    if cfg.pretrain.simulator != "none":
        holdout = plan_holdout(root, cfg.select.holdout, cfg.seed)
        prior, _ = fit_physics(root, cfg, device)
        init = pretrain_weights(root, out, cfg, cfg.model, prior, holdout, info, device)
    run = training.build_run(sim.net, train_ds, cfg.data, cfg.optim, cfg.seed, info, device)
    border = sim.net.reach_px  # K // 2, more with multi-scale kernels
    loop = EpochLoop(run=run, forward=forward_fn(run.net, cfg.model.coc_scale_px), loss=loss_fn(border, cfg.optim.grad_weight),
                     validate=lambda: validate(sim, val_ds, info, device, cfg.data.val_pairs), model_config=asdict(cfg.model),
                     config=cfg.to_dict(), defaults=asdict(ModelConfig()))
    fresh = (lambda: sim.net.load_state_dict(init)) if init is not None else (lambda: init_view_gain(sim, train_ds))
    return run_epochs(loop, out, resume=resume, on_fresh_start=fresh, on_epoch_end=on_epoch_end)


def fit_physics(root: Path, cfg: TrainConfig, device: torch.device) -> tuple[BaseModel, str]:
    """The physical model a physics-first network starts from, fitted on ``root``'s train crops exactly as
    ``dp5k evaluate`` fits ``base`` (its ``--fit-pairs`` crops, from the same start), and its spec as JSON (with the
    start of the fit, ``fit_start``, and the simulator it came from, ``source``).

    Raises:
        BadInputError: ``physics.simulator`` is not ``base`` or ``diagnosed:REPORT.json``, or its report is unusable.
    """
    spec = SimulatorSpec.parse(cfg.physics.simulator)
    if spec.name not in ("base", "diagnosed"):
        raise BadInputError(f"physics.simulator must be base or diagnosed:REPORT.json, got {spec}", where="config")
    spec.check_files()
    model = spec.load()
    assert isinstance(model, BaseModel)
    start = dict(model.params)
    batches = _fit_batches(root, cfg.physics.fit_pairs, cfg.physics.fit_crop_px, device)
    if batches:
        model.to(device).fit(batches)
    model = model.cpu().eval()
    text = json.dumps({**model_to_spec(model), "fit_start": start, "source": str(spec)})
    return build_prior(replace(ModelConfig(), prior_spec=text)), text


@torch.no_grad()
def pair_scores(views: Callable[[DPBatch], tuple[Tensor, Tensor]], ds: PhysicalPairs, device: torch.device) -> dict[str, list[float]]:
    """Per pair of ``ds`` the masked PSNR / SSIM / MAE (mean of L and R) of ``views(batch)``."""
    out: dict[str, list[float]] = {"psnr": [], "ssim": [], "mae": []}
    for i in range(len(ds.ids)):
        b = collate_dp([ds[i]]).to(device)
        left, right = views(b)
        m = view_metrics(left.float(), right.float(), b.left, b.right, b.valid)
        for k in out:
            out[k].append(float(m[k][0]))
    return out


def decide(network: dict[str, list[float]], physical: dict[str, list[float]], clusters: list[str], keep: str,
           physics_name: str, how: str) -> dict[str, Any]:
    """Keep the network or the physical model (:attr:`~neural_dp.config.SelectConfig.keep`), from both models'
    per-pair validation scores; ``clusters`` group the pairs for the bootstrap (their scenes: a tile is its own)."""
    if keep not in ("better", "network", "physical"):
        raise BadInputError(f"select.keep must be better, network or physical, got {keep!r}", where="config")
    n = len(clusters)
    note = ""
    if len(set(clusters)) < MIN_CLUSTERS:  # an interval over one or two scenes says nothing: resample the pairs
        note = f"; {len(set(clusters))} scene(s), so the pairs are resampled as if independent"
        clusters = [str(i) for i in range(n)]
    rs = Resampler(clusters, 1)
    d = rs.difference(network["psnr"], physical["psnr"])
    d_ssim = rs.difference(network["ssim"], physical["ssim"])
    better = n >= 2 and d.lo > 0 and d_ssim.mean >= 0
    kept = "network" if keep == "network" or (keep == "better" and better) else "physical"
    how = how + note
    gain = f"{d.mean:+.2f} dB PSNR [{d.lo:+.2f}, {d.hi:+.2f}] and {d_ssim.mean:+.4f} SSIM"
    if kept == "network":
        why = (f"kept the network: on the {n} validation pairs ({how}) it scores {gain} against the physical model "
               f"({physics_name})" + ("" if better or keep == "better" else "; select.keep = network keeps it whatever it scores"))
    elif keep == "physical":
        why = f"kept the physical model ({physics_name}) as select.keep = physical asks (the network: {gain} on the {n} validation pairs)"
    else:
        reason = ("one validation pair cannot tell" if n < 2 else
                  "its PSNR gain is not resolved (the 95 % interval reaches 0)" if d.lo <= 0 else "its SSIM is lower")
        why = (f"kept the physical model ({physics_name}): on the {n} validation pairs ({how}) the network scores {gain}, "
               f"and {reason}; best.pt renders exactly the physical model")
    return {"kept": kept, "why": why, "psnr_gain": d.to_json(), "ssim_gain": d_ssim.to_json(), "pairs": n}


def _mean(scores: dict[str, list[float]]) -> dict[str, float]:
    return {k: float(np.nanmean(v)) for k, v in scores.items()}


def _train_physical(root: Path, out: Path, cfg: TrainConfig, holdout: Holdout, info: RankInfo, device: torch.device,
                    resume: bool, on_epoch_end: Callable[[int, dict[str, float]], None] | None) -> TrainResult:
    """The physics-first default (module docstring)."""
    out.mkdir(parents=True, exist_ok=True)
    if info.is_main:
        for w in holdout.warnings:
            logger.warning("%s: %s", root, w)
    last = out / "last.pt"
    if resume and last.is_file():  # the physical model the run started from (refitting could only say the same)
        spec_text = str(load_checkpoint(last).get("model_config", {}).get("prior_spec", ""))
        prior = build_prior(replace(ModelConfig(), prior_spec=spec_text))
    else:
        prior, spec_text = fit_physics(root, cfg, device)
    model_cfg = replace(cfg.model, prior_spec=spec_text)
    physics_name = json.loads(spec_text).get("source", "base") if spec_text else "base"
    sim = new_simulator(model_cfg, cfg.seed, device)
    crop = CropSpec(cfg.data.crop_px, cfg.data.min_valid_fraction, vflip=cfg.data.vflip)
    train_ds = PhysicalPairs(root, holdout.train, prior, crop=crop, augment=cfg.augment, seed=cfg.seed,
                             length=cfg.data.samples_per_epoch)
    val_ds = PhysicalPairs(root, holdout.val, prior, seed=cfg.seed)
    physical = pair_scores(lambda b: (b.prior_left, b.prior_right), val_ds, device)
    if info.is_main:
        m = _mean(physical)
        logger.info("physical model (%s) on the %d validation pairs: PSNR %.2f dB, SSIM %.4f", physics_name,
                    len(holdout.val), m["psnr"], m["ssim"])
    init = pretrain_weights(root, out, cfg, model_cfg, prior, holdout, info, device)
    run = training.build_run(sim.net, train_ds, cfg.data, cfg.optim, cfg.seed, info, device)
    loop = EpochLoop(run=run, forward=forward_fn(run.net, model_cfg.coc_scale_px, sim),
                     loss=loss_fn(sim.net.reach_px, cfg.optim.grad_weight),
                     validate=lambda: validate(sim, val_ds, info, device, cfg.data.val_pairs), model_config=asdict(model_cfg),
                     config=cfg.to_dict(), defaults=asdict(ModelConfig()), patience=cfg.select.patience,
                     best_name=NETWORK_CKPT, select=cfg.select.metric)
    result = run_epochs(loop, out, resume=resume, on_epoch_end=on_epoch_end,
                        on_fresh_start=(lambda: sim.net.load_state_dict(init)) if init is not None else None)
    net_path = out / NETWORK_CKPT
    if net_path.is_file():
        best = NeuralDPSimulator.from_checkpoint(net_path, map_location=device).to(device)
        network = pair_scores(best, val_ds, device)
    else:  # no epoch ran (epochs = 0): the network is its initialisation, the physical model
        network = physical
    reader = DatasetReader(root)
    decision = decide(network, physical, [reader.params(p).scene for p in holdout.val], cfg.select.keep, physics_name,
                      holdout.how)
    report = {"dataset": str(root), "validation": holdout.to_json(), "physics": {"simulator": physics_name, "spec": json.loads(spec_text)},
              "physical_val": _mean(physical), "network_val": _mean(network), "per_pair": {"physical": physical, "network": network},
              "best_epoch": result.best_epoch, "epochs_done": result.epochs_done, "steps": result.steps,
              "pretrain": str(out / "pretrain") if init is not None else None, **decision}
    if info.is_main:
        if decision["kept"] == "network":
            shutil.copyfile(net_path, out / "best.pt.tmp")
            os.replace(out / "best.pt.tmp", out / "best.pt")
        else:
            physical_sim = new_simulator(replace(model_cfg, prior="physical"), cfg.seed, torch.device("cpu"))
            save_checkpoint(out / "best.pt", {"model": physical_sim.net.state_dict(), "model_config": asdict(physical_sim.cfg),
                                              "config": cfg.to_dict(), "epoch": 0, "step": 0,
                                              "best_val_ssim": report["physical_val"]["ssim"], "best_epoch": 0,
                                              "history": [], "decision": decision["why"]})
        write_json_atomic(out / REPORT, report)
        logger.info("%s", decision["why"])
    D.barrier(info)
    result.report = report
    return result


def pretrain_weights(root: Path, out: Path, cfg: TrainConfig, model_cfg: ModelConfig, prior: BaseModel, holdout: Holdout,
                     info: RankInfo, device: torch.device) -> dict[str, Tensor] | None:
    """The network's weights after calibrated pre-training (:mod:`neural_dp.pretrain`), or None when
    ``pretrain.simulator`` asks for none."""
    name = cfg.pretrain.simulator
    if name == "none":
        return None
    from .pretrain import pretrain

    return pretrain(root, out / "pretrain", cfg, model_cfg, SimulatorSpec.parse(name), prior, holdout, info, device)
