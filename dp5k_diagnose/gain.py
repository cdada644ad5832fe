"""Measure an extension's gain on held-out pairs: masked PSNR, SSIM, MAE before/after, bootstrap CI over pairs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neural_dp.metrics import view_metrics

from .data import Sample

Predict = Callable[[Sample], tuple[Tensor, Tensor]]


@dataclass
class PairMetrics:
    """Per-pair metrics (each the mean over the L and R views), arrays of length n_pairs."""

    pair_ids: list[str]
    psnr: np.ndarray
    ssim: np.ndarray
    mae: np.ndarray


def pair_metrics(predict: Predict, samples: list[Sample]) -> PairMetrics:
    ids, ps, ss, ms = [], [], [], []
    with torch.no_grad():
        for s in samples:
            l, r = predict(s)
            m = view_metrics(l.clamp(0, 1), r.clamp(0, 1), s.batch.left, s.batch.right, s.batch.valid)
            ids += list(s.batch.pair_ids)
            ps.append(m["psnr"].numpy())
            ss.append(m["ssim"].numpy())
            ms.append(m["mae"].numpy())
    return PairMetrics(ids, np.concatenate(ps), np.concatenate(ss), np.concatenate(ms))


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


def gain_report(before: PairMetrics, after: PairMetrics, split: str, n_boot: int = 2000, seed: int = 0) -> dict:
    """The ``gain`` object of report.json (means over pairs) plus per-pair PSNR gains."""
    d = after.psnr - before.psnr
    lo, hi = bootstrap_ci(d, n_boot, seed=seed)
    return {
        "split": split,
        "n_pairs": int(before.psnr.size),
        "psnr_before": float(np.nanmean(before.psnr)),
        "psnr_after": float(np.nanmean(after.psnr)),
        "ssim_before": float(np.nanmean(before.ssim)),
        "ssim_after": float(np.nanmean(after.ssim)),
        "mae_before": float(np.nanmean(before.mae)),
        "mae_after": float(np.nanmean(after.mae)),
        "psnr_gain_ci95": [lo, hi],
        "per_pair_psnr_gain": {pid: float(x) for pid, x in zip(before.pair_ids, d)},
    }
