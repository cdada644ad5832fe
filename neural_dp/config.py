"""The Neural DP Simulator's training configuration: :class:`TrainConfig`, a TOML file and ``section.key=value``
overrides (the loader and the shared sections are :mod:`dp5k_learn.config`'s).

Example ``train.toml`` (every key optional; defaults follow the paper and the released code)::

    seed = 0
    device = "auto"          # "cpu", "cuda", "cuda:1" or "auto"
    [data]
    crop_px = 256
    batch_size = 8
    [model]
    base_channels = 64
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
class TrainConfig:
    """Everything a training run depends on."""

    seed: int = 0
    device: str = "auto"
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (),
                base: TrainConfig | None = None) -> TrainConfig:
    """Defaults, then the TOML (or JSON) file, then ``section.key=value`` overrides, in that order."""
    return learn_config.load_config(path, overrides, base or TrainConfig())
