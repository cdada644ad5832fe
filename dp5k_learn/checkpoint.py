"""Checkpoints: plain tensors and Python primitives only, written atomically, read with ``weights_only=True``.

A checkpoint is a dict::

    {"model": state_dict, "model_config": {...}, "config": {...}, "optim": ..., "sched": ...,
     "epoch": completed epochs, "step": optimiser steps, "best_val_ssim": float, "best_epoch": int,
     "history": [{"epoch", "loss", "val_ssim", "val_psnr", "val_mae", "lr"}, ...]}

``last.pt`` is rewritten after every epoch (resume); ``best.pt`` whenever validation SSIM improves.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from dp5k_common.errors import BadInputError
from dp5k_common.io import atomic_path


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> Path:
    """Write ``state`` to ``path`` through a temporary file and an atomic rename."""
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return Path(path)


def load_checkpoint(path: str | os.PathLike[str], map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint safely (``weights_only=True``: no arbitrary code).

    Raises:
        BadInputError: missing or unreadable file.
    """
    if not os.path.isfile(path):
        raise BadInputError("checkpoint not found", where=path)
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure to unpickle is a bad file
        raise BadInputError(f"not a readable checkpoint ({type(exc).__name__})", where=path) from exc
    if not isinstance(state, dict) or "model" not in state:
        raise BadInputError("not a dp5k checkpoint (no 'model')", where=path)
    return state
