"""Which training data makes the suite's deblurrer transfer to another renderer's pairs (issue 33, section 2).

For every training set below, over ``--seeds`` seeds (seed k draws the studio data with seed 3 + k and trains with
seed k), the suite's deblurrer (``dp5k_testing.deblur_transfer.SUITE_TRAIN_ARGS``: 300 steps, 12 channels, 48 px crops)
is trained through ``dp5k deblur train`` and scored on every pair of 24 scenes x f/1.8, f/4 from each renderer of
``--renderers`` (``dp5k_testing.deblur_transfer.foreign_pairs``): the PSNR gain over the blurred input L + R, its mean
over seeds and scenes with a 95 % interval from a bootstrap over both (seeds and scenes resampled), and per |CoC| bin
for the first seed on the first renderer (why it fails).

Training sets (96 x 64 studio pairs, all-in-focus ``sharp``):

* ``narrow``: the issue's (10 scenes, f/2 and f/4 at each scene's own focus, the rig's full-frame sensor, no noise);
* ``diverse``: 60 scenes, one random capture each (focus, f-number 1.8-5.6, sensor format 0.2-12 px p99 CoC at
  f/1.8, gain 1-30 x the nominal noise; ``dp5k studio make-dataset --random-captures 1``);
* ``diverse`` with one ingredient taken out: ``no-noise``, ``nominal-noise`` (gain 1), ``rig-sensor`` (no format
  draw), ``10-scenes`` (10 scenes x 6 captures: as many pairs, fewer scenes), ``coc-1-12`` (the format range of the
  first diverse set, 1-12 px: no capture nearly all in focus).

Beside each renderer's gain it prints, for the first seed, the mean gain on the pairs whose blurred input is already
within noise of ``sharp`` (input PSNR above :data:`NEAR_SHARP_DB`) and on the others: a deblurrer that sharpens
what is sharp loses many dB on the first kind (docs/deblur.md).

Usage::

    python benchmarks/deblur_transfer.py OUT [--seeds 3] [--variants narrow,diverse,...] [--renderers aperture,...]

Runs resume (finished trainings are reused). Prints the date, load and commit, writes ``OUT/results.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from click.testing import CliRunner

from dp5k_cli import main as dp5k
from dp5k_common.dataset import DatasetReader
from dp5k_deblur.train import load_deblurrer
from dp5k_learn.data import CropSpec, DPPairDataset, collate_dp
from dp5k_testing.deblur_transfer import (RENDERERS, SUITE_TRAIN_ARGS, diverse_studio_pairs, foreign_pairs,
                                          narrow_studio_pairs, transfer_gain)
from run_info import record_result

VARIANTS: dict[str, Callable[[Path, int], Path]] = {
    "narrow": lambda out, seed: narrow_studio_pairs(out, seed),
    "diverse": lambda out, seed: diverse_studio_pairs(out, seed),
    "no-noise": lambda out, seed: diverse_studio_pairs(out, seed, ("--no-noise",)),
    "nominal-noise": lambda out, seed: diverse_studio_pairs(out, seed, ("--noise-gain", "1:1")),
    "rig-sensor": lambda out, seed: diverse_studio_pairs(out, seed, ("--coc-px", "rig")),
    "10-scenes": lambda out, seed: diverse_studio_pairs(out, seed, ("--scenes", "10", "--random-captures", "6")),
    "coc-1-12": lambda out, seed: diverse_studio_pairs(out, seed, ("--coc-px", "1:12")),
}
COC_BINS_PX = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 1e9)
"""|CoC| bin edges of the error table, px."""
BOOTSTRAP = 4000
NEAR_SHARP_DB = 45.0
"""Input PSNR (dB) above which a test pair counts as already sharp (its L + R within about the noise of ``sharp``)."""


def header() -> str:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip() or "unknown"
    load = "/".join(f"{v:.1f}" for v in os.getloadavg())
    return f"{datetime.datetime.now().isoformat(timespec='seconds')}, commit {commit}, load {load} on {os.cpu_count()} cores"


def bootstrap_ci(gains: np.ndarray, rng: np.random.Generator) -> tuple[float, float]:
    """95 % interval of the mean of ``gains`` (seeds x scenes), resampling seeds and scenes."""
    S, N = gains.shape
    means = [gains[np.ix_(rng.integers(0, S, S), rng.integers(0, N, N))].mean() for _ in range(BOOTSTRAP)]
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


@torch.no_grad()
def coc_bins(checkpoint: Path, dataset: Path) -> list[tuple[str, float, float, float]]:
    """Per |CoC| bin: (bin, share of pixels, MSE of the prediction, MSE of L + R) over every pair of ``dataset``."""
    net = load_deblurrer(checkpoint)
    reader = DatasetReader(dataset)
    acc = np.zeros((len(COC_BINS_PX) - 1, 3))
    for split in (s for s in reader.splits if reader.ids(s)):
        ds = DPPairDataset(dataset, split, CropSpec(), cache=False)
        for i in range(len(ds.ids)):
            b = collate_dp([ds[i]])
            err_p = ((net(b.left, b.right) - b.sharp) ** 2).mean(1)[0].numpy()
            err_i = ((b.left + b.right - b.sharp) ** 2).mean(1)[0].numpy()
            c = b.coc_px.abs()[0, 0].numpy()
            for k in range(len(COC_BINS_PX) - 1):
                m = (c >= COC_BINS_PX[k]) & (c < COC_BINS_PX[k + 1])
                acc[k] += (m.sum(), err_p[m].sum(), err_i[m].sum())
    return [(f"{COC_BINS_PX[k]:g}-{COC_BINS_PX[k + 1]:g}" if COC_BINS_PX[k + 1] < 1e9 else f">{COC_BINS_PX[k]:g}",
             n / acc[:, 0].sum(), p / n, i / n) for k, (n, p, i) in enumerate(acc) if n]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--renderers", default=",".join(RENDERERS))
    a = ap.parse_args()
    torch.set_num_threads(1)
    out: Path = a.out
    variants = [v.strip() for v in a.variants.split(",") if v.strip()]
    renderers = [r.strip() for r in a.renderers.split(",") if r.strip()]
    print(f"# deblur transfer: {header()}", flush=True)
    tests = {}
    for r in renderers:
        tests[r] = out / "test" / r
        if not (tests[r] / "dataset.json").is_file():
            foreign_pairs(tests[r], r)
    results: dict = {"header": header(), "seeds": a.seeds, "train_args": list(SUITE_TRAIN_ARGS), "variants": {}}
    rng = np.random.default_rng(0)
    for v in variants:
        t0 = time.perf_counter()
        per_seed: dict[str, list[dict[str, float]]] = {r: [] for r in renderers}
        pairs: dict[str, list[dict]] = {r: [] for r in renderers}
        for k in range(a.seeds):
            data, run = out / "data" / f"{v}-{k}", out / "runs" / f"{v}-{k}"
            if not (data / "dataset.json").is_file():
                VARIANTS[v](data, 3 + k)
            res = CliRunner().invoke(dp5k, ["-q", "deblur", "train", str(data), "--out", str(run), *SUITE_TRAIN_ARGS, "--seed", str(k)])
            if res.exit_code != 0:
                raise SystemExit(f"{v} seed {k}: {res.output}")
            for r in renderers:
                g = transfer_gain(run / "last.pt", tests[r])
                per_seed[r].append(g.scene_gain)
                pairs[r].append({"pairs": g.pairs, "input_psnr": g.input_psnr})
        row = {}
        for r in renderers:
            scenes = sorted(per_seed[r][0])
            gains = np.array([[s[sc] for sc in scenes] for s in per_seed[r]])
            lo, hi = bootstrap_ci(gains, rng)
            row[r] = {"mean_gain_db": float(gains.mean()), "ci95_db": [lo, hi], "per_seed_db": gains.mean(1).tolist(),
                      "input_psnr_db": pairs[r][0]["input_psnr"], "pairs": pairs[r]}
        results["variants"][v] = {**row, "wall_s": time.perf_counter() - t0}
        for r in renderers:
            p0 = pairs[r][0]["pairs"]
            near = [a - b for a, b in p0.values() if b > NEAR_SHARP_DB]
            rest = [a - b for a, b in p0.values() if b <= NEAR_SHARP_DB]
            row[r]["seed0_near_sharp"] = {"pairs": len(near), "mean_gain_db": float(np.mean(near)) if near else None,
                                          "others_mean_gain_db": float(np.mean(rest)) if rest else None}
        cells = "  ".join(f"{r}: {row[r]['mean_gain_db']:+.3f} [{row[r]['ci95_db'][0]:+.3f}, {row[r]['ci95_db'][1]:+.3f}]"
                          + (f" (near-sharp {row[r]['seed0_near_sharp']['pairs']}: {row[r]['seed0_near_sharp']['mean_gain_db']:+.2f},"
                             f" others {row[r]['seed0_near_sharp']['others_mean_gain_db']:+.3f})" if row[r]["seed0_near_sharp"]["pairs"] else "")
                          for r in renderers)
        print(f"{v:<14} {cells}   ({time.perf_counter() - t0:.0f} s)", flush=True)
    first = renderers[0]
    print(f"\nper |CoC| bin, seed 0, {first} (share of pixels, MSE x 1e4 of the prediction / of L + R, gain dB):")
    for v in [x for x in ("narrow", "diverse") if x in variants]:
        bins = coc_bins(out / "runs" / f"{v}-0" / "last.pt", tests[first])
        results["variants"][v]["coc_bins"] = bins
        print(f"  {v:<8} " + "  ".join(f"{b}: {s:.2f} {p * 1e4:.2f}/{i * 1e4:.2f} {10 * np.log10(i / p):+.2f}" for b, s, p, i in bins))
    (out / "results.json").write_text(json.dumps(results, indent=1))
    print(f"\ninput PSNR (L + R): " + ", ".join(f"{r} {results['variants'][variants[0]][r]['input_psnr_db']:.2f} dB" for r in renderers))
    record_result("deblur-transfer", "Training data that transfers: the suite's deblurrer's PSNR gain over L + R on other renderers' pairs (dB)",
                  ["training set"] + renderers + ["wall s"],
                  [[v] + [f"{x[r]['mean_gain_db']:+.2f} [{x[r]['ci95_db'][0]:+.2f}, {x[r]['ci95_db'][1]:+.2f}]" for r in renderers]
                   + [f"{x['wall_s']:.0f}"] for v, x in results["variants"].items()],
                  notes=f"Mean over {a.seeds} seeds x 24 scenes x f/1.8, f/4 with a 95 % bootstrap interval over seeds and scenes; "
                        "input PSNR (L + R): " + ", ".join(f"{r} {results['variants'][variants[0]][r]['input_psnr_db']:.2f} dB" for r in renderers) + ".")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
