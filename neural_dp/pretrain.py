"""Calibrated pre-training: the network first learns a physical simulator's renders of the target camera's own
train pairs, then fine-tunes on their measured views (:func:`neural_dp.train.train`, ``pretrain.simulator``).

Generic studio scenes teach a network effects of some camera; this data is the target camera's own: its train pairs'
sharp images and depth, rendered by a simulator calibrated on them (the physical model ``dp5k train`` fitted, or a
``dp5k diagnose`` report of those pairs, ``diagnosed:REPORT.json``), **refocused** so that the blur spans CoCs of
both signs and of several sizes (a planar target photo has one CoC; a network trained on it alone has seen one
blur). Refocusing keeps the lens, aperture and depth and moves the focus distance: for each train pair and variant
``v`` the focus is set so that the pair's median valid CoC becomes ``c_v`` (``pretrain.variants`` values spread
evenly over ``[-m, m]``, ``m`` = ``pretrain.max_coc_px``), and the CoC map is recomputed by Eq. 6 from the depth.
Nothing of ``dp5k_studio`` is used.

For a physics-first network whose start is the same simulator, the renders equal its own output: pre-training would
teach it nothing, so ``dp5k train`` skips it (``pretrain.simulator = auto``); a diagnosed model's renders over a
base-model start teach it what the diagnosed effects change, at every CoC. For the paper's network
(``model.prior = none``) it replaces pre-training on the studio.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from dp5k_common.dataset import DatasetReader, Pair
from dp5k_common.optics import coc_diameter_px
from dp5k_common.sharding import RankInfo
from dp5k_learn import training
from dp5k_learn.checkpoint import load_checkpoint
from dp5k_learn.data import CropSpec
from dp5k_learn.epochs import EpochLoop, run_epochs

from .augment import PhysicalPairs, render_prior
from .config import TrainConfig
from .holdout import Holdout
from .model import ModelConfig
from .simulators.base import BaseModel
from .simulators.catalog import SimulatorSpec

logger = logging.getLogger(__name__)


def refocus_mm(depth_mm: float, coc_px: float, focal_mm: float, f_number: float, pitch_mm: float) -> float:
    """The focus distance (mm) at which a point at ``depth_mm`` has the signed CoC ``coc_px`` (Eq. 6 solved for F):
    ``F = (d + C k f) / (1 + C k)``, ``k = N d / f^2``, C in mm on the sensor.

    >>> round(refocus_mm(1500.0, float(coc_diameter_px(1500.0, 1000.0, 50.0, 4.0, 0.05)), 50.0, 4.0, 0.05), 6)
    1000.0
    """
    c = coc_px * pitch_mm
    k = f_number * depth_mm / focal_mm**2
    return (depth_mm + c * k * focal_mm) / (1.0 + c * k)


def coc_targets(n: int, max_coc_px: float) -> list[float]:
    """``n`` CoCs spread evenly over [-max, max] (px)."""
    if n <= 1:
        return [max_coc_px]
    return [float(v) for v in np.linspace(-max_coc_px, max_coc_px, n)]


@torch.no_grad()
def refocused(pair: Pair, coc_px: float, simulator: BaseModel, tag: str) -> Pair | None:
    """``pair`` refocused so that its median valid CoC is ``coc_px``, its views the ``simulator``'s render; None when
    no focus distance beyond the focal length gives that CoC."""
    p = pair.params
    valid = pair.valid
    if not valid.any():
        return None
    d = float(np.median(pair.depth_mm[valid]))
    lo = -0.9 * p.focal_length_mm**2 / (p.f_number * d * p.pixel_pitch_mm)  # the CoC of focus at infinity, nearly
    c = max(coc_px, lo)
    F = refocus_mm(d, c, p.focal_length_mm, p.f_number, p.pixel_pitch_mm)
    if not (math.isfinite(F) and F > 1.05 * p.focal_length_mm):
        return None
    coc = coc_diameter_px(pair.depth_mm, F, p.focal_length_mm, p.f_number, p.pixel_pitch_mm).astype(np.float32)
    coc = np.where(valid, coc, np.nan).astype(np.float32)
    params = replace(p, pair_id=f"{p.pair_id}@{tag}", focus_distance_mm=float(F))
    new = Pair(params, pair.sharp, pair.left, pair.right, pair.depth_mm, coc)
    left, right = render_prior(simulator, new)
    return dataclasses.replace(new, left=left, right=right)


def calibrated_pairs(reader: DatasetReader, ids: list[str], simulator: BaseModel, targets: list[float]) -> dict[str, Pair]:
    """Every pair of ``ids`` refocused to each CoC of ``targets`` and rendered by ``simulator``."""
    out = {}
    for pid in ids:
        pair = reader.load(pid)
        for i, c in enumerate(targets):
            new = refocused(pair, c, simulator, f"v{i}")
            if new is not None:
                out[new.params.pair_id] = new
    return out


def max_coc(reader: DatasetReader, ids: list[str], cfg: TrainConfig) -> float:
    """``pretrain.max_coc_px``, or twice the largest |CoC| of the train pairs (at least 8 px)."""
    if cfg.pretrain.max_coc_px > 0:
        return float(cfg.pretrain.max_coc_px)
    m = 0.0
    for pid in ids:
        pair = reader.load(pid)
        if pair.valid.any():
            m = max(m, float(np.abs(pair.coc_px[pair.valid]).max()))
    return max(8.0, 2.0 * m)


def pretrain(root: Path, out: Path, cfg: TrainConfig, model_cfg: ModelConfig, spec: SimulatorSpec, prior: BaseModel,
             holdout: Holdout, info: RankInfo, device: torch.device) -> dict[str, Tensor]:
    """Pre-train a network of ``model_cfg`` on ``spec``'s calibrated renders (module docstring) in ``out`` (its own
    ``last.pt`` / ``best.pt``: a re-run resumes) and return its best weights. ``spec`` is ``base`` (the run's fitted
    physical model, ``prior``) or ``diagnosed:REPORT.json`` (fitted on the train crops as evaluate fits it)."""
    from .train import fit_physics, forward_fn, init_view_gain, loss_fn, new_simulator, validate

    if spec.name == "base":
        simulator = prior
    else:
        simulator, _ = fit_physics(root, replace(cfg, physics=replace(cfg.physics, simulator=str(spec))), device)
    reader = DatasetReader(root)
    m = max_coc(reader, holdout.train, cfg)
    targets = coc_targets(cfg.pretrain.variants, m)
    train_pairs = calibrated_pairs(reader, holdout.train, simulator, targets)
    val_pairs = calibrated_pairs(reader, holdout.val, simulator, targets)
    if info.is_main:
        logger.info("pre-training on %d renders of %s (the train pairs refocused to CoCs %s px)", len(train_pairs), spec,
                    ", ".join(f"{c:+.1f}" for c in targets))
    out.mkdir(parents=True, exist_ok=True)
    crop = CropSpec(cfg.data.crop_px, cfg.data.min_valid_fraction, vflip=cfg.data.vflip)
    train_ds = PhysicalPairs(None, list(train_pairs), prior, crop=crop, augment=cfg.augment, seed=cfg.seed,
                             length=cfg.data.samples_per_epoch, pairs=train_pairs)
    val_ds = PhysicalPairs(None, list(val_pairs), prior, seed=cfg.seed, pairs=val_pairs)
    sim = new_simulator(model_cfg, cfg.seed, device)
    optim = replace(cfg.optim, epochs=cfg.pretrain.epochs)
    run = training.build_run(sim.net, train_ds, cfg.data, optim, cfg.seed, info, device)
    loop = EpochLoop(run=run, forward=forward_fn(run.net, model_cfg.coc_scale_px, sim), loss=loss_fn(sim.net.reach_px, optim.grad_weight),
                     validate=lambda: validate(sim, val_ds, info, device, cfg.data.val_pairs), model_config=asdict(model_cfg),
                     config={**cfg.to_dict(), "pretrain_renders": str(spec)}, defaults=asdict(ModelConfig()),
                     patience=cfg.select.patience, select=cfg.select.metric)
    fresh = None if sim.physical else (lambda: init_view_gain(sim, train_ds))
    run_epochs(loop, out, resume=True, on_fresh_start=fresh, desc="pre-train")
    return load_checkpoint(out / "best.pt", map_location=device)["model"]
