"""The config sections every training run shares, and the one loader: defaults, a TOML file, ``section.key=value``.

A run's config is a frozen dataclass of sections (``neural_dp.config.TrainConfig``,
``dp5k_deblur.config.DeblurTrainConfig``): its own ``model`` section beside :class:`DataConfig` and
:class:`OptimConfig`. :func:`load_config` fills any such dataclass from a file and overrides; files are read
with :mod:`tomllib` (data only, no code); the resolved config is saved as ``config.json`` beside the
checkpoints and inside each checkpoint.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, TypeVar

from dp5k_common.errors import BadInputError

C = TypeVar("C")

@dataclass(frozen=True)
class DataConfig:
    """What the network sees."""

    crop_px: int = 256
    """Side of the square random training crops (the released code: 512 from 1024 ROIs); 0 = whole images."""
    batch_size: int = 8
    """Per-process batch size (the released code: 8)."""
    samples_per_epoch: int = 0
    """Training items per epoch (0 = one per training pair); random crops make repeats useful on small sets."""
    min_valid_fraction: float = 0.8
    """Crops with less valid depth are redrawn (the released code: 0.8)."""
    vflip: bool = True
    """Random vertical flips (p = 0.5), which keep the horizontal DP geometry."""
    num_workers: int = 0
    """DataLoader worker processes."""
    val_pairs: int = 0
    """Validate on at most this many val pairs (0 = all), full resolution."""


@dataclass(frozen=True)
class OptimConfig:
    """Adam with cosine annealing (Sec. 5), stepped per iteration."""

    epochs: int = 100
    lr: float = 5e-4
    lr_min: float = 1e-6
    grad_weight: float = 1.0
    """Weight of the gradient (edge) terms of Eq. (8)."""
    grad_clip: float = 1.0
    """Clip the global gradient norm to this (0 = off)."""
    amp: bool = True
    """bfloat16 autocast on CUDA (never on CPU)."""


@dataclass(frozen=True)
class FinetuneConfig:
    """Fine-tuning an existing network for exactly ``steps`` Adam steps on train crops, without epochs
    (:func:`dp5k_learn.setup.finetune`; ``dp5k diagnose --simulator neural:CKPT`` fine-tunes its structural
    extension and an equally fine-tuned control with it). The step is :func:`dp5k_learn.setup.optimiser_step`,
    the one every training run takes; the loss and clipping settings default to :class:`OptimConfig`'s."""

    steps: int = 150
    lr: float = 5e-5
    """Peak learning rate of the simulator's own (trained) weights, cosine-annealed to 0. Low, so that
    fine-tuning does not undo a well-trained checkpoint: at 5e-4 a control lost 0.8-1.0 dB in 150 steps
    (docs/diagnose.md, Limits)."""
    new_lr_mult: float = 100.0
    """Learning-rate factor of parameters a structural extension adds (the caller names them, e.g. the Neural DP
    network's ``scale_head.*``: they start at zero blend and must travel further than the trained ones); no
    effect on a network without them."""
    crop_px: int = 96
    """Side of the square random crops (0 = whole images)."""
    batch_size: int = 4
    seed: int = 0
    """Seeds crops, their order and dropout: two runs with the same settings see identical batches."""
    border_px: int | None = None
    """Loss border (px) cut from the valid mask; None = the network's kernel reach."""
    grad_weight: float = OptimConfig.grad_weight
    grad_clip: float = OptimConfig.grad_clip


def _coerce(value: Any, current: Any, key: str) -> Any:
    if isinstance(current, bool):
        if isinstance(value, str):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
        if isinstance(value, bool):
            return value
        raise BadInputError(f"'{key}' must be true/false, got {value!r}", where="config")
    try:
        if isinstance(current, int):
            if isinstance(value, float) and not value.is_integer():
                raise ValueError
            return int(value)
        if isinstance(current, float):
            return float(value)
        return str(value)
    except (TypeError, ValueError) as exc:
        kind = {int: "an integer", float: "a number"}.get(type(current), "a string")
        raise BadInputError(f"'{key}' must be {kind}, got {value!r}", where="config") from exc


def _apply(obj: Any, updates: dict[str, Any], prefix: str = "") -> Any:
    names = {f.name: f for f in fields(obj)}
    changes: dict[str, Any] = {}
    for key, value in updates.items():
        if key not in names:
            raise BadInputError(f"unknown config key '{prefix}{key}' (known: {', '.join(names)})", where="config")
        current = getattr(obj, key)
        if is_dataclass(current):
            if not isinstance(value, dict):
                raise BadInputError(f"'{prefix}{key}' is a section, got {value!r}", where="config")
            changes[key] = _apply(current, value, f"{prefix}{key}.")
        else:
            changes[key] = _coerce(value, current, prefix + key)
    return replace(obj, **changes)


def from_dict(obj: dict[str, Any], base: C) -> C:
    """``base`` (a dataclass of sections) with nested dict updates; unknown keys are errors."""
    return _apply(base, obj)


def load_config(path: str | Path | None, overrides: list[str] | tuple[str, ...], base: C) -> C:
    """``base`` (a run's defaults), then the TOML (or JSON) file, then ``section.key=value`` overrides, in that order.

    Raises:
        BadInputError: missing or unparsable file, unknown key, a value of the wrong type, a malformed override.
    """
    cfg = base
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise BadInputError("config file not found", where=p)
        try:
            data = json.loads(p.read_text()) if p.suffix == ".json" else tomllib.loads(p.read_text())
        except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise BadInputError(f"cannot parse config: {exc}", where=p) from exc
        cfg = from_dict(data, cfg)
    for item in overrides:
        if "=" not in item:
            raise BadInputError(f"override {item!r} must look like section.key=value", where="config")
        dotted, value = item.split("=", 1)
        parts = dotted.strip().split(".")
        nested: dict[str, Any] = {parts[-1]: value.strip()}
        for part in reversed(parts[:-1]):
            nested = {part: nested}
        cfg = from_dict(nested, cfg)
    return cfg
