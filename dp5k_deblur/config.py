"""The deblurrer's training configuration: the same sections, TOML files and ``section.key=value`` overrides as
``dp5k train`` (:mod:`dp5k_learn.config`), with a :class:`~dp5k_deblur.model.DeblurNetConfig` as the model.

Example ``deblur.toml`` (every key optional)::

    seed = 0
    [data]
    crop_px = 64
    batch_size = 8
    [model]
    base_channels = 16
    levels = 3
    [optim]
    epochs = 20
    lr = 3e-4
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from dp5k_learn.config import DataConfig, OptimConfig, load_config
from dp5k_learn.losses import CHARBONNIER_EPS

from .model import DeblurNetConfig

DEBLUR_DATA = DataConfig(crop_px=64, batch_size=8, min_valid_fraction=0.0, vflip=True)
"""Small random crops; depth validity does not limit a deblurring crop (its target, ``sharp``, is everywhere)."""
DEBLUR_OPTIM = OptimConfig(epochs=20, lr=3e-4, lr_min=1e-6, grad_weight=0.0, grad_clip=1.0)
"""Adam with cosine annealing and the plain Charbonnier loss (``grad_weight`` adds Eq. (8)'s gradient terms)."""


@dataclass(frozen=True)
class DeblurTrainConfig:
    """Everything a deblurrer's training run depends on."""

    seed: int = 0
    device: str = "auto"
    charbonnier_eps: float = CHARBONNIER_EPS
    """Charbonnier epsilon, linear intensity (the paper's 1e-3: nearly L1). Below it the loss is quadratic: short runs
    learn much faster with a larger one (200 steps on small studio pairs: +0.03 dB over L + R at 1e-3, +0.57 dB
    with MSE; docs/deblur.md)."""
    data: DataConfig = field(default_factory=lambda: DEBLUR_DATA)
    model: DeblurNetConfig = field(default_factory=DeblurNetConfig)
    optim: OptimConfig = field(default_factory=lambda: DEBLUR_OPTIM)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def load_deblur_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (),
                       base: DeblurTrainConfig | None = None) -> DeblurTrainConfig:
    """Defaults, then the TOML (or JSON) file, then ``section.key=value`` overrides (BadInputError on unknown keys)."""
    return load_config(path, overrides, base or DeblurTrainConfig())
