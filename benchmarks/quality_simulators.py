"""Full Table-2-style comparison on studio data with realistic effects (its last run: docs/results.md).

Steps: render a studio dataset with planted physical effects (``dp5k studio make-dataset``), train the
Neural DP Simulator on its train split twice with the same budget (``dp5k train``): as it trains by default
(physics first, keep-the-better) and the paper's network (``model.prior=none``), evaluate every simulator on the
held-out test split (``dp5k evaluate``), print the Markdown table and the settings.

Usage::

    python benchmarks/quality_simulators.py OUT [--scenes 12] [--size 192x128] [--epochs 12] [--device cpu]

Everything it writes goes under OUT (dataset, run folder with checkpoints, evaluation with figures).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


from dp5k_studio.dataset import make_dataset  # noqa: E402  (benchmarks may use the world)
from neural_dp.config import load_config
from neural_dp.evaluate import evaluate
from neural_dp.train import train
from run_info import machine, markdown_table, record_result

EFFECTS = {"lr_gain_imbalance": 1.0, "psf_profile": 1.0, "disparity_scale": 1.0, "field_varying_psf": 1.0,
           "chromatic_defocus": 1.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--size", default="192x128")
    ap.add_argument("--epochs", type=int, default=12)
    ap.add_argument("--samples-per-epoch", type=int, default=128)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--channels", type=int, default=16)
    ap.add_argument("--levels", type=int, default=4)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    W, H = (int(v) for v in args.size.split("x"))
    ds = args.out / "studio"
    t0 = time.perf_counter()
    if not (ds / "dataset.json").is_file():
        make_dataset(ds, scenes=args.scenes, effects=EFFECTS, size=(W, H), seed=args.seed)
    t_data = time.perf_counter() - t0
    overrides = [f"device={args.device}", f"seed={args.seed}", f"data.crop_px={args.crop}", "data.batch_size=4",
                 f"data.samples_per_epoch={args.samples_per_epoch}", f"model.base_channels={args.channels}",
                 f"model.levels={args.levels}", f"optim.epochs={args.epochs}", f"optim.lr={args.lr}"]
    t0 = time.perf_counter()
    paper = train(ds, args.out / "run_paper", load_config(None, overrides + ["model.prior=none"]))
    t_paper = time.perf_counter() - t0
    t0 = time.perf_counter()
    run = train(ds, args.out / "run", load_config(None, overrides))
    t_train = time.perf_counter() - t0
    specs = ["disk", "butterworth", "raytrace", "base", f"neural:{args.out / 'run_paper' / 'best.pt'}",
             f"neural:{args.out / 'run' / 'best.pt'}"]
    res = evaluate(ds, args.out / "eval", split="test", simulators=specs, device=args.device, figures=2)
    names = list(res.means)
    table_md = res.table_md.replace(f"| {names[4]} | {names[5]} |", "| Neural DP, paper's network | Neural DP (dp5k train default) |")
    settings = {"effects": EFFECTS, "scenes": args.scenes, "size": [W, H], "train_overrides": overrides,
                "paper": {"best_epoch": paper.best_epoch, "best_val_ssim": paper.best_val_ssim, "steps": paper.steps},
                "default": {"best_epoch": run.best_epoch, "steps": run.steps, "kept": run.report.get("kept"),
                            "why": run.report.get("why")},
                "seconds": {"dataset": round(t_data, 1), "train_paper": round(t_paper, 1), "train_default": round(t_train, 1)}}
    (args.out / "settings.json").write_text(json.dumps(settings, indent=2))
    print(table_md)
    print(json.dumps(settings, indent=2))
    print(machine())
    record_result("table2-studio", "Table 2 on studio data with realistic effects", *markdown_table(table_md),
                  notes=f"Effects {', '.join(f'{k}={v}' for k, v in EFFECTS.items())}; {args.scenes} scenes at {W} x {H}; "
                        f"Neural DP {args.channels} channels x {args.levels} levels, {run.steps} steps as dp5k train makes it "
                        f"by default ({run.report.get('why')}), and the paper's network with the same budget ({paper.steps} "
                        f"steps, best val SSIM {paper.best_val_ssim:.4f} at epoch {paper.best_epoch}); dataset {t_data:.0f} s, "
                        f"training {t_train:.0f} s (default) and {t_paper:.0f} s (paper's network).")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
