"""Measure an extension's gain on held-out pairs: masked PSNR, SSIM, MAE before/after, bootstrap CIs over pairs
and over tiles within each pair."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from dp5k_common.errors import BadInputError
from dp5k_learn.metrics import view_metrics

from .data import Sample

Predict = Callable[[Sample], tuple[Tensor, Tensor]]


def tile_sums(x: Tensor, mask: Tensor, tile: int) -> tuple[Tensor, Tensor]:
    """Per-tile sums of ``x`` (B, C, H, W) over channels and masked pixels, and per-tile counts of masked pixels x
    channels, each (B * n_tiles_y * n_tiles_x,)."""
    t = min(tile, x.shape[-2], x.shape[-1])
    s = F.avg_pool2d(x.sum(1, keepdim=True) * mask, t, stride=t) * t * t
    c = F.avg_pool2d(mask, t, stride=t) * t * t * x.shape[1]
    return s.reshape(-1), c.reshape(-1)


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


@dataclass
class TileErrors:
    """Squared errors of a prediction per pair, view and tile over the ``predictable`` pixels (:data:`MASKS`).

    ``sse``: (n_pairs, 2, n_tiles), summed over the view's channels and the tile's scored pixels (linear
    intensity squared); ``count``: (n_pairs, n_tiles), scored pixels x channels per tile (the same for L and
    R). Tiles cover the whole image (the last row and column may be partial), so a pair's PSNR from the
    summed tiles is exactly its masked PSNR (:func:`dp5k_learn.metrics.masked_psnr`)."""

    pair_ids: list[str]
    sse: np.ndarray
    count: np.ndarray


def tile_errors(predict: Predict, samples: list[Sample], tile_px: int) -> TileErrors:
    """:class:`TileErrors` of ``predict`` (clamped to [0, 1], as the metrics are) in ``tile_px`` tiles."""
    ids: list[str] = []
    sse: list[np.ndarray] = []
    count: list[np.ndarray] = []
    with torch.no_grad():
        for s in samples:
            l, r = predict(s)
            h, w = s.score.shape[-2:]
            pad = (0, -w % tile_px, 0, -h % tile_px)
            m = F.pad(s.score.to(l.dtype), pad)
            per_view = []
            for pred, gt in ((l, s.batch.left), (r, s.batch.right)):
                e, c = tile_sums(F.pad((pred.clamp(0, 1) - gt) ** 2, pad), m, tile_px)
                per_view.append(e.reshape(l.shape[0], -1).double().numpy())
            sse.append(np.stack(per_view, 1))
            count.append(c.reshape(l.shape[0], -1).double().numpy())
            ids += list(s.batch.pair_ids)
    return TileErrors(ids, np.concatenate(sse), np.concatenate(count))


def tile_psnr(e: TileErrors, weights: np.ndarray | None = None) -> np.ndarray:
    """Per-pair PSNR (dB, the mean over L and R) from tile sums, with each tile counted ``weights`` times
    (``(..., n_pairs, n_tiles)``; None: once). Returns (..., n_pairs); NaN where a pair scores no pixel."""
    w = np.ones_like(e.count) if weights is None else weights
    n = (w * e.count).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        mse = np.stack([(w * e.sse[:, v]).sum(-1) for v in (0, 1)]) / n
        psnr = -10.0 * np.log10(np.maximum(mse, 1e-20))
    return np.where(n > 0, psnr.mean(0), np.nan)


def tile_bootstrap_ci(before: TileErrors, after: TileErrors, n_boot: int = 2000, level: float = 0.95,
                      seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap CI of the mean over pairs of the PSNR gain (dB) ``after`` - ``before``,
    resampling the scored tiles *within* each pair (stratified: every pair keeps its weight).

    The interval is conditional on the held-out captures: it covers what their sensor noise and the
    sampling of their content over the frame leave uncertain, not how other scenes would differ. Tiles are
    independent under that noise (it is independent per pixel; a 32 px tile dwarfs demosaicking's reach),
    and resampling tiles whose expected gains differ only widens the interval. Over the 4 held-out pairs
    of a 24-pair set a bootstrap over pairs has 35 distinct resamples, and its lower bound is nearly the
    worst pair's gain (:func:`bootstrap_ci`)."""
    if before.pair_ids != after.pair_ids or before.count.shape != after.count.shape:
        raise ValueError("tile_bootstrap_ci: before and after must cover the same pairs and tiles")
    rng = np.random.default_rng(seed)
    n_pairs, n_tiles = before.count.shape
    weights = np.zeros((n_boot, n_pairs, n_tiles))
    for i in range(n_pairs):
        scored = np.flatnonzero(before.count[i] > 0)
        if scored.size:
            weights[:, i, scored] = rng.multinomial(scored.size, np.full(scored.size, 1.0 / scored.size), size=n_boot)
    gains = tile_psnr(after, weights) - tile_psnr(before, weights)  # (n_boot, n_pairs)
    ok = np.isfinite(gains).all(0)
    if not ok.any():
        return (0.0, 0.0)
    means = gains[:, ok].mean(1)
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
