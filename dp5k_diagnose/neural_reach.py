"""The Neural DP Simulator's reach: error against |CoC| for 5 x 5 kernels, and the gain of a larger kernel.

The paper's simulator predicts 5 x 5 per-pixel kernels plus additive residuals, so blur wider than 5 px must
come from the residual images. This study trains the same small network twice on the same data and budget,
once with the paper's 5 x 5 kernels and once with a wider kernel (the structural extension), and reports the
held-out masked PSNR per |CoC| bin for both, with a bootstrap CI (over pairs) of the per-bin gain.

Usage: ``python -m dp5k_diagnose.neural_reach DATASET OUT [--epochs N] [--kernel K]``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dp5k_common.dataset import DatasetReader
from dp5k_common.io import write_json_atomic

from .data import full_samples, load_pairs
from .gain import bootstrap_ci

BINS_PX = (0.0, 2.0, 4.0, 8.0, 16.0, math.inf)


def per_bin_psnr(sim: Any, samples: list, bins: tuple[float, ...] = BINS_PX) -> np.ndarray:
    """(n_pairs, n_bins) masked PSNR of L and R together per |CoC| bin (NaN where a bin is empty)."""
    rows = []
    with torch.no_grad():
        for s in samples:
            l, r = sim(s.batch)
            e2 = ((l.clamp(0, 1) - s.batch.left) ** 2 + (r.clamp(0, 1) - s.batch.right) ** 2).mean(1) / 2  # (B, H, W)
            a = s.batch.coc_px[:, 0].abs()
            v = s.batch.valid[:, 0]
            for i in range(e2.shape[0]):
                row = []
                for lo, hi in zip(bins[:-1], bins[1:]):
                    m = v[i] & (a[i] >= lo) & (a[i] < hi)
                    row.append(10 * math.log10(1.0 / max(float(e2[i][m].mean()), 1e-12)) if int(m.sum()) >= 50 else float("nan"))
                rows.append(row)
    return np.array(rows)


def neural_reach_study(dataset: str | Path, out: str | Path, kernel: int = 11, epochs: int = 6, seed: int = 0) -> dict[str, Any]:
    """Train 5 x 5 and ``kernel`` x ``kernel`` variants, compare per |CoC| bin on the test split."""
    from neural_dp.config import DataConfig, OptimConfig, TrainConfig
    from neural_dp.model import ModelConfig
    from neural_dp.simulators.registry import get_simulator
    from neural_dp.train import train

    out = Path(out)
    reader = DatasetReader(dataset)
    held = full_samples(load_pairs(reader, reader.ids("test") or reader.ids("val")))
    res: dict[str, Any] = {"bins_px": [[lo, hi if math.isfinite(hi) else None] for lo, hi in zip(BINS_PX[:-1], BINS_PX[1:])], "kernels": {}}
    per = {}
    for k in (5, kernel):
        cfg = TrainConfig(seed=seed, device="cpu",
                          data=DataConfig(crop_px=64, batch_size=4, samples_per_epoch=64, vflip=False),
                          model=ModelConfig(base_channels=8, levels=2, kernel_size=k, norm="group", tile_px=0),
                          optim=OptimConfig(epochs=epochs, lr=2e-3, amp=False))
        tr = train(dataset, out / f"k{k}", cfg)
        sim = get_simulator("neural", checkpoint=out / f"k{k}" / "best.pt")
        sim.eval()
        per[k] = per_bin_psnr(sim, held)
        res["kernels"][str(k)] = {"best_val_ssim": tr.best_val_ssim, "psnr_per_bin": [float(x) if np.isfinite(x) else None for x in np.nanmean(per[k], 0)]}
    gain = per[kernel] - per[5]
    res["gain_per_bin"] = []
    for j in range(gain.shape[1]):
        g = gain[:, j]
        g = g[np.isfinite(g)]
        res["gain_per_bin"].append({"mean_db": float(g.mean()) if g.size else None, "ci95": list(bootstrap_ci(g, seed=seed)) if g.size else None, "n_pairs": int(g.size)})
    write_json_atomic(out / "neural_reach.json", res)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("out")
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--kernel", type=int, default=11)
    a = ap.parse_args()
    print(json.dumps(neural_reach_study(a.dataset, a.out, a.kernel, a.epochs), indent=1))


if __name__ == "__main__":
    main()
