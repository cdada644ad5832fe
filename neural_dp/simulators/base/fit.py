"""Levenberg-Marquardt fitting of a base model's (and its components') named scalar parameters."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ...batch import DPBatch

if TYPE_CHECKING:
    from .model import BaseModel

__all__ = ["fit_parameters"]


def _masked_residual(model: BaseModel, batch: DPBatch, field: Tensor | None, layers: tuple[Tensor, Tensor] | None = None,
                     mask: Tensor | None = None) -> Tensor:
    left, right = model.render(batch, field, layers)
    m = (batch.valid if mask is None else mask).float()
    r = torch.cat([(left - batch.left) * m, (right - batch.right) * m], dim=1)
    return r.reshape(-1)


@torch.no_grad()
def fit_parameters(
    model: BaseModel,
    targets: Sequence[tuple[object, str]],
    batches: list[DPBatch],
    fields: list[Tensor] | None = None,
    iters: int = 4,
    masks: list[Tensor] | None = None,
) -> float:
    """Levenberg-Marquardt fit of named scalar parameters on the masked L/R squared error.

    Args:
        model: the model to fit (parameters are changed in place).
        targets: ``(owner, name)`` pairs; ``owner`` is the model or one of its components, each holding
            ``params``, ``bounds`` and ``steps`` dicts.
        batches: measured batches (left/right set).
        fields: optional per-batch field maps (for crops).
        iters: LM iterations (each costs 1 + len(targets) renders per batch; the gain costs none).
        masks: optional per-batch (B, 1, H, W) masks of the pixels that count (default: ``batch.valid``).

    Returns:
        The final mean squared error.
    """
    fields = fields or [None] * len(batches)
    masks = masks or [b.valid for b in batches]
    post_only = all(o is model and n == "gain" or getattr(o, "post_only", False) for o, n in targets)
    cache = [model.render_layers_only(b, f) for b, f in zip(batches, fields)] if post_only else [None] * len(batches)

    def get() -> np.ndarray:
        return np.array([o.params[n] for o, n in targets], dtype=np.float64)  # type: ignore[attr-defined]

    def put(x: np.ndarray) -> None:
        for (o, n), v in zip(targets, x):
            lo, hi = o.bounds.get(n, (-np.inf, np.inf))  # type: ignore[attr-defined]
            o.params[n] = float(np.clip(v, lo, hi))  # type: ignore[attr-defined]

    def residual() -> Tensor:
        with torch.no_grad():
            return torch.cat([_masked_residual(model, b, f, c, m) for b, f, c, m in zip(batches, fields, cache, masks)]).double()

    x = get()
    r = residual()
    cost = float((r**2).sum())
    lam = 1e-3
    for _ in range(iters):
        cols = []
        for i, (o, n) in enumerate(targets):
            if o is model and n == "gain":
                # views are linear in the gain: d r / d g = (r + measured) / g
                meas = torch.cat([torch.cat([b.left * m, b.right * m], 1).reshape(-1) for b, m in zip(batches, masks)]).double()
                cols.append((r + meas) / max(model.params["gain"], 1e-6))
                continue
            h = o.steps.get(n, 1e-2)  # type: ignore[attr-defined]
            xp = x.copy()
            lo, hi = o.bounds.get(n, (-np.inf, np.inf))  # type: ignore[attr-defined]
            if xp[i] + h > hi:
                h = -h
            xp[i] += h
            put(xp)
            cols.append((residual() - r) / h)
            put(x)
        J = torch.stack(cols, 1)
        JtJ = (J.T @ J).numpy()
        Jtr = (J.T @ r).numpy()
        improved = False
        for _try in range(4):
            A = JtJ + lam * np.diag(np.diag(JtJ) + 1e-12)
            try:
                dx = -np.linalg.solve(A, Jtr)
            except np.linalg.LinAlgError:
                dx = -np.linalg.lstsq(A, Jtr, rcond=None)[0]
            put(x + dx)
            r_new = residual()
            c_new = float((r_new**2).sum())
            if c_new < cost:
                x, r, cost = get(), r_new, c_new
                lam = max(lam / 5, 1e-6)
                improved = True
                break
            put(x)
            lam *= 10
        if not improved:
            break
    put(x)
    return cost / max(r.numel(), 1)
