"""The paper's Table 2 on real pairs that nobody here rendered: every simulator scored on held-out real Sdirt tiles
(Canon EOS R6 II + RF50, split by photo), with 95 % intervals (its last run: docs/results.md).

Steps:

1. ``dp5k import sdirt SRC OUT/real --tile WxH``: the two planar targets, each photo one source; the 1.5 m photo's
   tiles are train, the 0.6 m photo's test (``--real DATASET`` takes any other ``dp5k import`` with train and test
   splits instead).
2. ``dp5k diagnose`` (its library, CLI defaults) of the base model on the real **train** tiles only: a copy of the train photo's tiles, every
   third held out as diagnose's test split (diagnose confirms its causes on its test split, so the real test photo
   must not be there); its report makes the ``diagnosed`` simulator.
3. The Neural DP Simulator, per seed: pre-trained on the studio (``dp5k_studio.make_dataset`` with the realistic
   effects of the studio table, ``benchmarks/quality_simulators.py``), then fine-tuned on the real train tiles
   (``neural_dp.registry.finetune``: the training step of ``dp5k train``, a fixed number of steps).
4. ``dp5k evaluate``'s scoring (:func:`neural_dp.evaluate.evaluate`) of the peers (published defaults), the base
   model (fitted on train tiles, as evaluate does), the diagnosed model, and both Neural DP Simulators of every seed
   on the real test tiles: masked MAE / PSNR / SSIM, mean of the L and R views, per tile.
5. Means with 95 % intervals (:mod:`dp5k_learn.intervals`: tiles resampled, and seeds for the Neural DP rows), the
   PSNR differences between every two rows and which are resolved.

Usage::

    python benchmarks/table2_real.py OUT [--seeds 0,1,2] [--tile 128x128] [--steps 300] [--finetune-steps 150]

Writes OUT/table2_real.md and OUT/table2_real.json; prints them with the date, load, commit, wall and CPU time.
The fine-tuned checkpoints (``OUT/neural/real_s<k>.pt``) and the report (``OUT/diagnose/report.json``) can join the
downstream study (``benchmarks/study_downstream.py --simulator LABEL=neural:... --simulator LABEL=diagnosed:...``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from dp5k_common.dataset import DatasetReader, copy_pairs
from dp5k_common.io import write_bytes_atomic, write_json_atomic
from dp5k_learn.checkpoint import save_checkpoint
from dp5k_learn.config import FinetuneConfig
from dp5k_learn.intervals import Estimate, Resampler, verdict
from dp5k_diagnose.run import DiagnoseConfig, auto_fit_pairs, run_diagnose
from dp5k_studio.dataset import make_dataset  # noqa: E402  (benchmarks may use the world)
from neural_dp.evaluate import evaluate
from neural_dp.registry import PAPER_F_NUMBERS, NeuralDPSimulator, SimulatorSpec, finetune, train
from neural_dp.config import load_config
from quality_simulators import EFFECTS
from run_info import Stopwatch, machine, markdown_table, record_result

ROOT = Path(__file__).resolve().parents[1]
SDIRT = ROOT.parent / "shared" / "data" / "sdirt-canon-r6m2"
METRICS = ("psnr", "ssim", "mae")
HELD_OUT_EVERY = 3
"""Every third train tile (in id order, so spread over the field) is diagnose's held-out split."""


def dp5k(*args: str) -> None:
    """Run a dp5k command as a user would (its CPU time counts as this run's children)."""
    subprocess.run([sys.executable, "-m", "dp5k_cli", "-q", *args], check=True, cwd=ROOT)


def diagnose_train_tiles(real: Path, out: Path) -> Path:
    """``dp5k diagnose`` of the base model on ``real``'s train tiles only (a third held out); returns report.json."""
    report = out / "diagnose" / "report.json"
    if report.is_file():
        return report
    train_ids = DatasetReader(real).ids("train")
    held = train_ids[::HELD_OUT_EVERY]
    view = out / "diagnose_train_tiles"
    if not (view / "dataset.json").is_file():
        copy_pairs(real, view, {"train": [p for p in train_ids if p not in held], "val": [], "test": held},
                   source=f"the train tiles of {real}; every {HELD_OUT_EVERY}rd held out for diagnose's confirmation")
    # dp5k diagnose's own settings (CLI defaults), through its library: on main the command prints its summary with a
    # variable that a look-alike loop overwrites (KeyError 'split' after report.json is written, when there are look-alikes)
    run_diagnose(view, SimulatorSpec(), out / "diagnose", DiagnoseConfig(fit_pairs=auto_fit_pairs(view)))
    return report


def neural_pair(studio: Path, real: Path, out: Path, seed: int, a: argparse.Namespace) -> tuple[Path, Path]:
    """The studio-trained Neural DP checkpoint of ``seed`` (``best.pt``, by val SSIM on the studio's val scenes, as
    ``dp5k train`` selects) and the same fine-tuned on the real train tiles."""
    steps_per_epoch = 16
    cfg = load_config(None, [f"seed={seed}", "device=cpu", f"data.crop_px={a.crop}", f"data.batch_size={a.batch}",
                             f"data.samples_per_epoch={steps_per_epoch * a.batch}", f"model.base_channels={a.channels}",
                             f"model.levels={a.levels}", f"optim.epochs={max(1, a.steps // steps_per_epoch)}",
                             f"optim.lr={a.lr}"])
    studio_run = out / "neural" / f"studio_s{seed}"
    train(studio, studio_run, cfg)
    tuned = out / "neural" / f"real_s{seed}.pt"
    if not tuned.is_file():
        sim = NeuralDPSimulator.from_checkpoint(studio_run / "best.pt")
        ft = FinetuneConfig(steps=a.finetune_steps, lr=a.finetune_lr, crop_px=a.crop, batch_size=a.batch, seed=seed)
        losses = finetune(sim, real, ft, desc=f"fine-tune seed {seed}")
        save_checkpoint(tuned, {"model": sim.net.state_dict(), "model_config": asdict(sim.cfg),
                                "config": {"init_from": str(studio_run / "best.pt"), "finetune": asdict(ft),
                                           "dataset": str(real), "split": "train"},
                                "history": [{"step": i, "loss": v} for i, v in enumerate(losses)]})
    return studio_run / "best.pt", tuned


def table(metrics: dict[str, Any], rows: dict[str, list[str]], rs: Resampler, pair_ids: list[str]) -> tuple[list[dict[str, Any]], list[Any]]:
    """Each row (label -> its evaluate columns, one per seed) as means with intervals; every two rows' PSNR difference."""
    per_pair = metrics["per_pair"]
    grids = {label: {m: np.array([[per_pair[p][c][m] for p in pair_ids] for c in cols]) for m in METRICS}
             for label, cols in rows.items()}
    out = []
    for label, g in grids.items():
        row: dict[str, Any] = {"simulator": label, "seeds": len(rows[label])}
        for m in METRICS:
            row[m] = rs.estimate(g[m]).to_json()
        out.append(row)
    labels = list(grids)
    diffs = [rs.compare(x, grids[x]["psnr"], y, grids[y]["psnr"]) for i, x in enumerate(labels) for y in labels[i + 1:]]
    return out, diffs


def markdown(rows: list[dict[str, Any]], note: str) -> str:
    lines = [note, "", "| simulator | MAE [95 % CI] | PSNR (dB) [95 % CI] | SSIM [95 % CI] | seeds |", "|---|---|---|---|---|"]
    for r in rows:
        cell = {m: Estimate(r[m]["mean"], *r[m]["ci95"]) for m in METRICS}
        lines.append(f"| {r['simulator']} | {cell['mae'].text(4)} | {cell['psnr'].text(2)} | {cell['ssim'].text(4)} | {r['seeds']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--sdirt", type=Path, default=SDIRT, help="Sdirt DP119 or its real_sample_set (dp5k import sdirt SRC)")
    ap.add_argument("--real", type=Path, default=None, help="an existing dp5k import with train and test splits instead")
    ap.add_argument("--tile", default="128x128", help="dp5k import sdirt --tile (128x128: 24 tiles per photo)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--studio-scenes", type=int, default=16)
    ap.add_argument("--studio-size", default="192x128")
    ap.add_argument("--steps", type=int, default=320, help="pre-training steps on the studio")
    ap.add_argument("--finetune-steps", type=int, default=160, help="fine-tuning steps on the real train tiles")
    ap.add_argument("--finetune-lr", type=float, default=5e-4)
    ap.add_argument("--crop", type=int, default=96)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--channels", type=int, default=16)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--lr", type=float, default=2e-3)
    a = ap.parse_args(argv)
    seeds = [int(s) for s in a.seeds.split(",")]
    out: Path = a.out
    print(f"# Table 2 on real pairs: {machine()}", flush=True)
    clock = Stopwatch()
    real = a.real
    if real is None:
        real = out / "real"
        if not (real / "dataset.json").is_file():
            dp5k("import", "sdirt", str(a.sdirt), str(real), "--tile", a.tile)
    report = diagnose_train_tiles(real, out)
    print(f"diagnose: {json.loads(report.read_text())['cause']} ({clock})", flush=True)
    W, H = (int(v) for v in a.studio_size.lower().split("x"))
    studio = out / "studio"
    if not (studio / "dataset.json").is_file():
        make_dataset(studio, scenes=a.studio_scenes, effects=EFFECTS, size=(W, H), f_numbers=PAPER_F_NUMBERS, cameras=(0,), seed=7)
    neural = {seed: neural_pair(studio, real, out, seed, a) for seed in seeds}
    print(f"neural: trained ({clock})", flush=True)
    peers = ["disk", "butterworth", "raytrace", "base", f"diagnosed:{report}"]
    specs = peers + [f"neural:{n[0]}" for n in neural.values()] + [f"neural:{n[1]}" for n in neural.values()]
    evaluate(real, out / "eval", split="test", simulators=specs, figures=2)
    metrics = json.loads((out / "eval" / "metrics.json").read_text())
    columns = dict(zip((str(SimulatorSpec.parse(s)) for s in specs), metrics["simulators"]))
    rows = {name: [columns[name]] for name in ("disk", "butterworth", "raytrace", "base")}
    rows["diagnosed (train tiles)"] = [columns[f"diagnosed:{report}"]]
    rows["Neural DP, studio only"] = [columns[f"neural:{n[0]}"] for n in neural.values()]
    rows["Neural DP, studio + real train tiles"] = [columns[f"neural:{n[1]}"] for n in neural.values()]
    reader = DatasetReader(real)
    pair_ids = metrics["pairs"]
    test_sources = sorted({reader.params(p).source_id for p in pair_ids})
    rs = Resampler([reader.params(p).scene for p in pair_ids], len(seeds))
    table_rows, diffs = table(metrics, rows, rs, pair_ids)
    note = (f"Held-out real test split of `{real}`: {len(pair_ids)} tiles of {len(test_sources)} photo(s) "
            f"({', '.join(test_sources)}); masked metrics of `dp5k evaluate` (mean of L and R, valid depth), mean over "
            f"tiles (and seeds {seeds} for the Neural DP rows); 95 % intervals from a bootstrap over the tiles (and the "
            f"seeds), {rs.n_clusters} clusters.")
    words = verdict(diffs)
    text = markdown(table_rows, note) + "\nPSNR differences:\n\n" + words
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    result = {"machine": machine(), "cost": str(clock), "real": str(real), "test_pairs": pair_ids, "test_sources": test_sources,
              "diagnose_report": str(report), "neural": {s: [str(p) for p in n] for s, n in neural.items()},
              "settings": settings, "rows": table_rows, "differences": [d.to_json() for d in diffs], "verdict": words}
    write_json_atomic(out / "table2_real.json", result)
    write_bytes_atomic(out / "table2_real.md", text.encode())
    print(text)
    print(f"{clock}; {machine()}")
    record_result("table2-real", "Table 2 on real pairs (Sdirt, split by photo)", *markdown_table(text),
                  notes=f"{note}\n\nPSNR differences: {words}\n\nCost: {clock}.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
