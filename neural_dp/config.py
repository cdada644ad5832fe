"""The Neural DP Simulator's training configuration: :class:`TrainConfig`, a TOML file and ``section.key=value``
overrides (the loader and the shared sections are :mod:`dp5k_learn.config`'s).

Example ``train.toml`` (every key optional; the defaults are what ``dp5k train`` does, :mod:`neural_dp.train`)::

    seed = 0
    device = "auto"          # "cpu", "cuda", "cuda:1" or "auto"
    [data]
    crop_px = 256
    batch_size = 8
    [model]
    prior = "physical"       # "none": the paper's network
    base_channels = 16
    levels = 3
    [physics]
    simulator = "base"       # or "diagnosed:REPORT.json"
    [augment]
    hflip_swap = 0.5
    [select]
    patience = 10
    [optim]
    epochs = 100
    lr = 5e-4

Files are read with :mod:`tomllib` (data only, no code); the resolved config is saved as ``config.json``
beside the checkpoints and inside each checkpoint.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from dp5k_learn import config as learn_config
from dp5k_learn.config import DataConfig, OptimConfig

from .model import ModelConfig


@dataclass(frozen=True)
class PhysicsConfig:
    """The physical model the network starts from (``model.prior = "physical"``) and is judged against."""

    simulator: str = "base"
    """``base`` (the physical base model) or ``diagnosed:REPORT.json`` (the base model with the effects a ``dp5k
    diagnose`` report of this camera's train pairs named and fitted)."""
    fit_pairs: int = 8
    """Train pairs (one crop each) its rim softness and gain are fitted on, as ``dp5k evaluate --fit-pairs`` does."""
    fit_crop_px: int = 256
    """Side of those crops (``dp5k evaluate``'s)."""


@dataclass(frozen=True)
class AugmentConfig:
    """Training augmentations that keep the DP geometry (:mod:`neural_dp.augment`)."""

    hflip_swap: float = 0.5
    """Probability of mirroring an item left-right **and swapping its L and R views** (the CoC keeps its sign): the
    mirror image of a scene seen by a left-right symmetric camera. The physical views are mirrored and swapped
    with it, and the network is told (its per-view gains follow the photodiodes)."""
    exposure: float = 0.2
    """Exposure scaling: sharp, views and physical views times ``exp(u)``, u uniform in [-x, x] (0 = off); blur is
    linear in light, so the physical views scale exactly."""


@dataclass(frozen=True)
class SelectConfig:
    """Validation, early stopping and the choice between the network and the physical model."""

    holdout: float = 0.25
    """Share of the train split held out for validation when the dataset has no val split: whole source photos
    when there are several, else spatially separate tiles of the one photo (:mod:`neural_dp.holdout`)."""
    metric: str = "psnr"
    """The validation metric that picks the network's best epoch and stops training early: ``psnr`` or ``ssim``
    (the paper's, which stays the choice of ``model.prior = none``)."""
    patience: int = 10
    """Stop after this many epochs without a better validation score (0 = never stop early)."""
    keep: str = "better"
    """``better``: keep the network only if it beats the physical model on the validation pairs (PSNR gain with a
    95 % interval above 0, SSIM not lower); else ``best.pt`` is the physical model itself. ``network``: keep the
    network whatever it scores (the paper's behaviour). ``physical``: always the physical model."""


@dataclass(frozen=True)
class PretrainConfig:
    """Calibrated pre-training (:mod:`neural_dp.pretrain`): the network first learns a physical simulator's renders of
    the train pairs' own sharp images and depth, refocused to CoCs of both signs, then fine-tunes on the measured
    views."""

    simulator: str = "none"
    """``none``, or the simulator whose renders the network learns first: ``base`` (the physical model the run fitted
    on the train pairs; for the paper's network, ``model.prior = none``, which must learn the physics before it can
    learn anything else) or ``diagnosed:REPORT.json`` (e.g. over a base-model start, to learn what the diagnosed
    effects change at every CoC). A physics-first network starting from the same simulator would learn nothing:
    its output already equals those renders."""
    variants: int = 6
    """Refocused renders per train pair."""
    max_coc_px: float = 0.0
    """Largest |CoC| of the refocused renders, px (0 = twice the largest |CoC| of the train pairs, at least 8)."""
    epochs: int = 30


def _train_model() -> ModelConfig:
    return ModelConfig(prior="physical", base_channels=16, levels=3)


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on."""

    seed: int = 0
    device: str = "auto"
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=_train_model)
    optim: OptimConfig = field(default_factory=OptimConfig)
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    select: SelectConfig = field(default_factory=SelectConfig)
    pretrain: PretrainConfig = field(default_factory=PretrainConfig)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (),
                base: TrainConfig | None = None) -> TrainConfig:
    """Defaults, then the TOML (or JSON) file, then ``section.key=value`` overrides, in that order."""
    return learn_config.load_config(path, overrides, base or TrainConfig())
