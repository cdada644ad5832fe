r"""Levenberg-Marquardt fitting of a base model's (and its components') named scalar parameters, and what a
fit's residual and Jacobian predict without refitting.

Parameters are ``(owner, name)`` targets: ``owner`` is the model (``gain``, ``rim_softness_px``,
``pixel_box``) or one of its components; each owner holds ``params``, ``bounds`` and ``steps`` (the finite
difference step, in the parameter's own units). Data are *samples*: objects with ``batch`` (a
:class:`dp5k_learn.batch.DPBatch` with measured views), ``field`` ((B, 2, H, W) field coordinates) and
``score`` ((B, 1, H, W) bool, the pixels that count), like :class:`dp5k_diagnose.data.Sample`.

:func:`jacobian` measures the residual :math:`r` (both views, the scored pixels, linear units) and its
Jacobian :math:`J` (forward differences, one render per parameter; parameters that only change the rendered
views reuse one layered render, and the gain's column is exact) once; :meth:`Linearization.solve` then gives,
for any set of parameters held at chosen values, the bounded Gauss-Newton refit of the others

.. math:: \min_d \lVert r + J d \rVert^2, \qquad lo \le \theta + d \le hi, \quad d_j = v_j - \theta_j \text{ for held } j

from the normal equations :math:`A = J^T J`, :math:`b = J^T r` (a P x P problem, P the parameter count):
diagnose compares many models that differ by which effects they hold (the model without each effect, an
effect swapped for a look-alike), all linear problems in the same Jacobian around a fitted model.
:func:`lm_fit` is Levenberg-Marquardt on the same pieces; :func:`fit_parameters` fits batches with it.
"""

from __future__ import annotations

import logging
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from scipy.linalg import solve_triangular
from scipy.optimize import lsq_linear
from torch import Tensor

from dp5k_learn.batch import DPBatch

if TYPE_CHECKING:
    from .model import BaseModel

__all__ = ["Linearization", "jacobian", "lm_fit", "clustered_intervals", "fit_parameters", "is_view_parameter", "get_values", "set_values"]

Sample = Any
"""A fit sample: ``batch``, ``field``, ``score`` (module docstring)."""

log = logging.getLogger(__name__)

Target = tuple[object, str]


def is_view_parameter(model: BaseModel, owner: object, name: str) -> bool:
    """True when ``name`` of ``owner`` only changes the rendered views after the layered render (the gain, a
    post-only component's parameters, a component's ``post_params``): its Jacobian column reuses one render."""
    if owner is model:
        return name == "gain"
    return bool(getattr(owner, "post_only", False)) or name in getattr(owner, "post_params", ())


def _scored(s: Sample) -> Tensor:
    """(B, 6, H, W) bool: the entries of both views' residual that count (the scored pixels, 6 channels)."""
    return s.score.expand(-1, 6, -1, -1)


_SCORED_INDEX: dict[int, tuple[weakref.ref, int, Tensor]] = {}
"""Per score map (by id, while it lives): (a reference to it, its version counter, the flat index)."""


def scored_values(s: Sample, e: Tensor) -> Tensor:
    """(n,) the entries of ``e`` (B, 6, H, W) at :func:`_scored`, in row-major order: ``e[_scored(s)]``, by a
    flat index kept per score map (a boolean mask is resolved again on every call, 15 x the cost of the gather
    on a (2, 6, 200, 200) residual; the index is measured again when the map changes in place)."""
    key = s.score
    hit = _SCORED_INDEX.get(id(key))
    if hit is None or hit[0]() is not key or hit[1] != key._version:
        k = id(key)
        ref = weakref.ref(key, lambda _r, k=k: _SCORED_INDEX.pop(k, None) if _SCORED_INDEX.get(k, (None,))[0] is _r else None)
        hit = (ref, key._version, torch.nonzero(_scored(s).reshape(-1)).squeeze(1))
        _SCORED_INDEX[k] = hit
    return e.reshape(-1).index_select(0, hit[2])


def residual_vector(model: BaseModel, samples: Sequence[Sample], layers: Sequence[tuple[Tensor, Tensor]] | None = None) -> Tensor:
    """(n,) float64: prediction minus measurement of both views at the scored pixels of every sample."""
    out = []
    for i, s in enumerate(samples):
        with torch.no_grad():
            l, r = model.render(s.batch, s.field, None if layers is None else layers[i])
        e = torch.cat([l - s.batch.left, r - s.batch.right], 1)
        out.append(scored_values(s, e).double())
    return torch.cat(out)


def get_values(targets: Sequence[Target]) -> np.ndarray:
    return np.array([o.params[n] for o, n in targets], dtype=np.float64)  # type: ignore[attr-defined]


def set_values(targets: Sequence[Target], x: np.ndarray) -> None:
    """Write ``x`` into the targets, clipped to their bounds."""
    for (o, n), v in zip(targets, x):
        lo, hi = o.bounds.get(n, (-np.inf, np.inf))  # type: ignore[attr-defined]
        o.params[n] = float(np.clip(v, lo, hi))  # type: ignore[attr-defined]


def bounds_of(targets: Sequence[Target]) -> tuple[np.ndarray, np.ndarray]:
    lo = np.array([o.bounds.get(n, (-np.inf, np.inf))[0] for o, n in targets], dtype=np.float64)  # type: ignore[attr-defined]
    hi = np.array([o.bounds.get(n, (-np.inf, np.inf))[1] for o, n in targets], dtype=np.float64)  # type: ignore[attr-defined]
    return lo, hi


@dataclass
class Linearization:
    """The residual and Jacobian of one model at parameters ``theta``.

    Attributes:
        targets: the parameters, ``(owner, name)``.
        theta: (P,) their values (each in its own units).
        r: (n,) float64 residual at ``theta`` (linear units).
        J: (n, P) float64 Jacobian of ``r`` (linear units per parameter unit); it may have been measured at a
            point one accepted step before ``theta`` (:func:`lm_fit`).
    """

    targets: list[Target]
    theta: np.ndarray
    r: Tensor
    J: Tensor

    def __post_init__(self) -> None:
        self.A = (self.J.T @ self.J).numpy()
        self.b = (self.J.T @ self.r).numpy()
        self.sse = float(self.r @ self.r)
        self.lo, self.hi = bounds_of(self.targets)

    def index(self, owner: object, name: str | None = None) -> list[int]:
        """Indices of ``owner``'s parameters (or of its parameter ``name``) among the targets."""
        return [i for i, (o, n) in enumerate(self.targets) if o is owner and (name is None or n == name)]

    def predicted_sse(self, theta: np.ndarray) -> float:
        """The squared error the linearization predicts at ``theta``."""
        d = theta - self.theta
        return float(self.sse + 2 * self.b @ d + d @ self.A @ d)

    def solve(self, held: dict[int, float] | None = None, damping: float = 0.0) -> np.ndarray:
        """The bounded Gauss-Newton refit: parameters in ``held`` (index -> value) fixed, the rest free.

        ``damping`` adds ``damping * diag(A)`` (Levenberg-Marquardt). Returns the (P,) parameter values."""
        held = held or {}
        P = len(self.targets)
        d = np.zeros(P)
        for j, v in held.items():
            d[j] = v - self.theta[j]
        free = [j for j in range(P) if j not in held]
        if not free:
            return self.theta + d
        A = self.A[np.ix_(free, free)].copy()
        A[np.diag_indices_from(A)] += damping * np.diag(A)
        hj = list(held)
        b = self.b[free] + (self.A[np.ix_(free, hj)] @ d[hj] if hj else 0.0)
        lo, hi = self.lo[free] - self.theta[free], self.hi[free] - self.theta[free]
        lo, hi = np.minimum(lo, 0.0), np.maximum(hi, 0.0)  # a start on a bound may stay there
        # min d'A d + 2 b'd  ==  min |L' d + L^-1 b|^2  with  A = L L'
        L = _cholesky(A)
        rhs = -solve_triangular(L, b, lower=True)
        df = lsq_linear(L.T, rhs, bounds=(lo, hi), method="bvls").x
        d[free] = df
        return self.theta + d


def _cholesky(A: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a positive semi-definite ``A``, with the smallest jitter on its diagonal that
    makes it positive definite (a parameter the data does not move has a zero column)."""
    scale = max(float(np.mean(np.diag(A))), 1e-30)
    jitter = 1e-12 * scale
    for _ in range(8):
        try:
            return np.linalg.cholesky(A + jitter * np.eye(len(A)))
        except np.linalg.LinAlgError:
            jitter *= 100
    return np.linalg.cholesky(A + scale * np.eye(len(A)))


def jacobian(model: BaseModel, targets: Sequence[Target], samples: Sequence[Sample], r: Tensor | None = None) -> Linearization:
    """The residual of ``model`` on ``samples`` and its forward-difference Jacobian in ``targets``.

    Costs one layered render per sample for the residual, plus one per parameter that acts before the views
    are formed; view parameters (:func:`is_view_parameter`) reuse the layers, and the gain's column is exact
    (the views are linear in it). ``r``, when given, is the residual at the current values (saves a render
    only where every target is a view parameter)."""
    targets = list(targets)
    x = get_values(targets)
    with torch.no_grad():
        layers = [model.render_layers_only(s.batch, s.field) for s in samples]
    r0 = residual_vector(model, samples, layers)
    cols: list[Tensor] = []
    for i, (o, n) in enumerate(targets):
        if o is model and n == "gain":
            meas = torch.cat([scored_values(s, torch.cat([s.batch.left, s.batch.right], 1)).double() for s in samples])
            cols.append((r0 + meas) / max(model.params["gain"], 1e-6))
            continue
        h = o.steps.get(n, 1e-2)  # type: ignore[attr-defined]
        lo, hi = o.bounds.get(n, (-np.inf, np.inf))  # type: ignore[attr-defined]
        if x[i] + h > hi:
            h = -h
        xp = x.copy()
        xp[i] += h
        set_values(targets, xp)
        h_eff = get_values(targets)[i] - x[i]
        if h_eff == 0.0:
            cols.append(torch.zeros_like(r0))
        else:
            rp = residual_vector(model, samples, layers if is_view_parameter(model, o, n) else None)
            cols.append((rp - r0) / h_eff)
        set_values(targets, x)
    J = torch.stack(cols, 1) if cols else torch.zeros(r0.numel(), 0, dtype=torch.float64)
    return Linearization(targets, x, r0, J)


def steps_of(targets: Sequence[Target]) -> np.ndarray:
    """(P,) each parameter's finite-difference step: its natural scale."""
    return np.array([o.steps.get(n, 1e-2) for o, n in targets], dtype=np.float64)  # type: ignore[attr-defined]


def broyden_update(lin: Linearization, theta: np.ndarray, r: Tensor) -> Linearization:
    r"""The linearization at ``theta`` (residual ``r``) with the Jacobian updated by Broyden's rank-one rule
    instead of measured again: :math:`J \leftarrow J + (\Delta r - J d) d^T / (d^T d)`, in parameters scaled by
    their finite-difference steps (their units differ by orders of magnitude)."""
    scale = steps_of(lin.targets)
    ds = (theta - lin.theta) / scale
    denom = float(ds @ ds)
    if denom <= 0:
        return Linearization(lin.targets, theta, r, lin.J)
    Js = lin.J * torch.from_numpy(scale)
    u = (r - lin.r) - Js @ torch.from_numpy(ds)
    Js = Js + torch.outer(u, torch.from_numpy(ds / denom))
    return Linearization(lin.targets, theta, r, Js / torch.from_numpy(scale))


def lm_fit(model: BaseModel, targets: Sequence[Target], samples: Sequence[Sample], iters: int, rel_tol: float = 1e-4,
           remeasure_every: int = 3) -> Linearization:
    """Levenberg-Marquardt on the squared error of ``samples``' scored pixels (bounded steps,
    :meth:`Linearization.solve`); ``model``'s parameters end at the best values found.

    The Jacobian is measured (:func:`jacobian`) at the start and after every ``remeasure_every`` accepted
    steps, and updated by Broyden's rule (:func:`broyden_update`, no render) in between. Stops when a step
    lowers the squared error by less than ``rel_tol`` of it, or none lowers it. Returns the linearization at
    the final values."""
    targets = list(targets)
    lin = jacobian(model, targets, samples)
    lam = 1e-3
    since = 0
    for it in range(iters):
        accepted = False
        for _ in range(5):
            x_new = lin.solve(damping=lam)
            set_values(targets, x_new)
            r_new = residual_vector(model, samples)
            sse_new = float(r_new @ r_new)
            if sse_new < lin.sse:
                accepted = True
                lam = max(lam / 5, 1e-7)
                break
            set_values(targets, lin.theta)
            lam *= 10
        if not accepted:
            if since == 0:
                break
            lin, since = jacobian(model, targets, samples), 0  # an updated Jacobian may have drifted: measure it
            continue
        x_new = get_values(targets)
        done = it == iters - 1 or (lin.sse - sse_new) < rel_tol * lin.sse
        since += 1
        if done or since < remeasure_every:
            lin = broyden_update(lin, x_new, r_new)
        else:
            lin, since = jacobian(model, targets, samples), 0
        if done:
            break
    set_values(targets, lin.theta)
    return lin


Z_95 = 1.959964
"""Two-sided 95 % quantile of the standard normal distribution."""


def entry_units(samples: Sequence[Sample]) -> tuple[np.ndarray, list[str]]:
    """(n,) unit index of every entry of :func:`residual_vector` (its pair: crops of one pair are one unit) and
    the units' pair ids."""
    ids: list[str] = []
    where: dict[str, int] = {}
    out = []
    for s in samples:
        counts = _scored(s).flatten(1).sum(1).tolist()
        for pid, c in zip(s.batch.pair_ids, counts):
            u = where.setdefault(pid, len(ids))
            if u == len(ids):
                ids.append(pid)
            out.append(np.full(int(c), u, dtype=np.int64))
    return (np.concatenate(out) if out else np.zeros(0, np.int64)), ids


def clustered_intervals(lin: Linearization, samples: Sequence[Sample]) -> np.ndarray:
    r"""(P, 2) 95 % intervals of the parameters, clustered over pairs: the sandwich covariance
    :math:`(J^T J)^{-1} \left(\frac{U}{U-1}\sum_u g_u g_u^T\right) (J^T J)^{-1}`, :math:`g_u = J_u^T r_u` summed
    over the entries of pair ``u``, the first-order variance of a bootstrap over pairs (it grows when pairs
    disagree and does not assume white noise); value +- 1.96 sd, clipped to the bounds. NaN rows with fewer
    than 2 pairs."""
    units, ids = entry_units(samples)
    P = len(lin.targets)
    if len(ids) < 2 or P == 0:
        return np.full((P, 2), np.nan)
    g = torch.zeros(len(ids), P, dtype=torch.float64)
    g.index_add_(0, torch.from_numpy(units), lin.J * lin.r[:, None])
    gn = g.numpy()
    meat = gn.T @ gn * len(ids) / (len(ids) - 1)
    inv = np.linalg.pinv(lin.A)
    sd = np.sqrt(np.maximum(np.diag(inv @ meat @ inv), 0.0))
    lo = np.maximum(lin.theta - Z_95 * sd, lin.lo)
    hi = np.minimum(lin.theta + Z_95 * sd, lin.hi)
    return np.stack([lo, hi], 1)


@torch.no_grad()
def fit_parameters(model: BaseModel, targets: Sequence[tuple[object, str]], batches: list[DPBatch], fields: list[Tensor] | None = None,
                   iters: int = 4, masks: list[Tensor] | None = None) -> float:
    """Levenberg-Marquardt (:func:`lm_fit`) of ``targets`` on the masked L/R squared error of ``batches``
    (measured views set; ``fields`` their field maps, default the whole image; ``masks`` the pixels that count,
    default ``batch.valid``), in place. Returns the final mean squared error over the counted entries."""
    from .field import field_coords

    samples = []
    for i, b in enumerate(batches):
        B, _, H, W = b.sharp.shape
        f = fields[i] if fields is not None and fields[i] is not None else field_coords(B, H, W, b.sharp.device)
        m = masks[i] if masks is not None else b.valid
        samples.append(SimpleNamespace(batch=b, field=f, score=m.bool()))
    lin = lm_fit(model, targets, samples, iters)
    return lin.sse / max(lin.r.numel(), 1)
