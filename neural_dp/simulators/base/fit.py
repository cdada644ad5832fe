"""Levenberg-Marquardt fitting of a base model's (and its components') named scalar parameters."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from dp5k_learn.batch import DPBatch

if TYPE_CHECKING:
    from .model import BaseModel

__all__ = ["fit_parameters", "parameter_intervals"]


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


Z_95 = 1.959964
"""Two-sided 95 % quantile of the standard normal distribution."""


@torch.no_grad()
def parameter_intervals(
    model: BaseModel,
    targets: Sequence[tuple[object, str]],
    batches: list[DPBatch],
    fields: list[Tensor] | None = None,
    masks: list[Tensor] | None = None,
) -> dict[tuple[int, str], tuple[float, float]]:
    r"""95 % intervals of fitted parameters, clustered over pairs (a linearised bootstrap over pairs).

    At the fitted values, with the masked residual :math:`r` of both views and its Jacobian :math:`J` (forward
    differences, as the fit's), the sandwich covariance
    :math:`(J^T J)^{-1} \left(\frac{n}{n-1}\sum_i g_i g_i^T\right) (J^T J)^{-1}`, :math:`g_i = J_i^T r_i` summed
    over the pixels of pair ``i`` (crops of one pair are one unit, ``batch.pair_ids``), is the first-order
    variance of a bootstrap over pairs: it grows when pairs disagree and does not assume white noise. Each
    interval is value +- 1.96 sd, clipped to the parameter's bounds (its units are the parameter's).

    Returns:
        ``{(id(owner), name): (lo, hi)}``; empty with fewer than 2 pairs or no target.
    """
    fields = fields or [None] * len(batches)
    masks = masks or [b.valid for b in batches]
    owners = [pid for b in batches for pid in b.pair_ids]
    units = sorted(set(owners))
    if len(units) < 2 or not targets:
        return {}

    def per_image(b: DPBatch, f: Tensor | None, m: Tensor) -> Tensor:
        return _masked_residual(model, b, f, None, m).double().reshape(b.sharp.shape[0], -1)

    r = [per_image(b, f, m) for b, f, m in zip(batches, fields, masks)]
    cols: list[list[Tensor]] = []
    for o, n in targets:
        x = o.params[n]  # type: ignore[attr-defined]
        h = o.steps.get(n, 1e-2)  # type: ignore[attr-defined]
        lo, hi = o.bounds.get(n, (-np.inf, np.inf))  # type: ignore[attr-defined]
        if x + h > hi:
            h = -h
        o.params[n] = x + h  # type: ignore[attr-defined]
        cols.append([(per_image(b, f, m) - ri) / h for b, f, m, ri in zip(batches, fields, masks, r)])
        o.params[n] = x  # type: ignore[attr-defined]
    P = len(targets)
    JtJ = np.zeros((P, P))
    g = {u: np.zeros(P) for u in units}
    k = 0
    for bi, ri in enumerate(r):
        J = torch.stack([c[bi] for c in cols], -1)  # (B, N, P)
        JtJ += torch.einsum("bnp,bnq->pq", J, J).numpy()
        gi = torch.einsum("bnp,bn->bp", J, ri).numpy()
        for row in gi:
            g[owners[k]] += row
            k += 1
    meat = sum(np.outer(v, v) for v in g.values()) * len(units) / (len(units) - 1)
    inv = np.linalg.pinv(JtJ)
    cov = inv @ meat @ inv
    out = {}
    for j, (o, n) in enumerate(targets):
        sd = float(np.sqrt(max(cov[j, j], 0.0)))
        x = float(o.params[n])  # type: ignore[attr-defined]
        lo, hi = o.bounds.get(n, (-np.inf, np.inf))  # type: ignore[attr-defined]
        out[(id(o), n)] = (float(max(x - Z_95 * sd, lo)), float(min(x + Z_95 * sd, hi)))
    return out
