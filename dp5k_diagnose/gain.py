"""Measure an extension's gain on held-out pairs: masked PSNR, SSIM, MAE before/after, bootstrap CI over pairs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from dp5k_common.errors import BadInputError
from dp5k_learn.metrics import view_metrics

from .data import Sample

Predict = Callable[[Sample], tuple[Tensor, Tensor]]


@dataclass
class PairMetrics:
    """Per-pair metrics (each the mean over the L and R views), arrays of length n_pairs."""

    pair_ids: list[str]
    psnr: np.ndarray
    ssim: np.ndarray
    mae: np.ndarray


MASKS = ("predictable", "valid")
"""Pixel masks the metrics can be taken over: ``predictable`` (:attr:`Sample.score`: valid pixels out of blur
reach of the frame border and of depth edges, the pixels diagnose fits and tests on) or all ``valid`` ones."""


def pair_metrics(predict: Predict, samples: list[Sample], mask: str = "valid") -> PairMetrics:
    """Per-pair masked PSNR, SSIM and MAE of ``predict`` over ``mask`` pixels (one of :data:`MASKS`); a pair
    without such pixels gets NaN."""
    return pair_metrics_by_mask(predict, samples, (mask,))[mask]


def pair_metrics_by_mask(predict: Predict, samples: list[Sample], masks: tuple[str, ...] = MASKS) -> dict[str, PairMetrics]:
    """:func:`pair_metrics` for several masks from one rendering of each sample."""
    for mask in masks:
        if mask not in MASKS:
            raise ValueError(f"unknown mask {mask!r} (known: {', '.join(MASKS)})")
    ids: list[str] = []
    acc: dict[str, dict[str, list[np.ndarray]]] = {m: {"psnr": [], "ssim": [], "mae": []} for m in masks}
    with torch.no_grad():
        for s in samples:
            l, r = predict(s)
            ids += list(s.batch.pair_ids)
            for mask in masks:
                where = s.score if mask == "predictable" else s.batch.valid
                m = view_metrics(l.clamp(0, 1), r.clamp(0, 1), s.batch.left, s.batch.right, where)
                for k in ("psnr", "ssim", "mae"):
                    acc[mask][k].append(m[k].numpy())
    return {mask: PairMetrics(ids, *(np.concatenate(acc[mask][k]) for k in ("psnr", "ssim", "mae"))) for mask in masks}


def bootstrap_ci(diff: np.ndarray, n_boot: int = 2000, level: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap CI of the mean of paired differences (resampling pairs)."""
    diff = np.asarray(diff, dtype=np.float64)
    diff = diff[np.isfinite(diff)]
    if diff.size == 0:
        return (0.0, 0.0)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, diff.size, (n_boot, diff.size))
    means = diff[idx].mean(1)
    a = (1 - level) / 2
    return float(np.quantile(means, a)), float(np.quantile(means, 1 - a))


def gain_report(before: PairMetrics, after: PairMetrics, split: str, n_boot: int = 2000, seed: int = 0, mask: str = "valid") -> dict:
    """The ``gain`` object of report.json (means over pairs with finite metrics) plus per-pair PSNR gains."""
    d = after.psnr - before.psnr
    if not np.isfinite(d).any():
        raise BadInputError(f"no pair of the {split} split has a pixel to measure the gain on ({mask} pixels)")
    lo, hi = bootstrap_ci(d, n_boot, seed=seed)

    def mean(x: np.ndarray) -> float:
        x = np.asarray(x, dtype=np.float64)
        return float(x[np.isfinite(x)].mean()) if np.isfinite(x).any() else 0.0

    return {
        "split": split,
        "mask": mask,
        "n_pairs": int(np.isfinite(d).sum()),
        "psnr_before": mean(before.psnr),
        "psnr_after": mean(after.psnr),
        "ssim_before": mean(before.ssim),
        "ssim_after": mean(after.ssim),
        "mae_before": mean(before.mae),
        "mae_after": mean(after.mae),
        "psnr_gain_ci95": [lo, hi],
        # a pair without a scored pixel (e.g. all within a depth edge's reach) is null here, out of the means and CI
        "per_pair_psnr_gain": {pid: (float(x) if np.isfinite(x) else None) for pid, x in zip(before.pair_ids, d)},
    }
