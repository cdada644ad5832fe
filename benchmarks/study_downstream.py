"""The downstream study: Tables 3 and 4 of the paper on two test sets, studio-measured
and real (Sdirt), with the Neural DP Simulator, several seeds and 95 % intervals. The figure in docs/results.md is a
reduced run of step 5 (``dp5k study downstream`` with smaller budgets) on the data steps 1-3 prepared, not a full run
of this script; a full run records itself there.

Steps:

1. RGBD frames: studio scenes rendered with their all-in-focus radiance as ``sharp`` (``make_dataset(...,
   all_in_focus_sharp=True)``), written as ``dp5k synthesize`` frames (image, depth, intrinsics): the stand-in
   for Hypersim, which cannot be fetched here.
2. "Measured" pairs: other studio scenes with planted physical effects and sensor noise (``--effects``), f/22
   ``sharp`` as in a capture, f/2 and f/4: the stand-in for DP5K's test split (``--measured 96`` scenes give 12
   test scenes, 24 test pairs, split by scene).
3. Real pairs: ``dp5k import sdirt`` of the shared Sdirt targets (split by photo; ``--real DATASET`` takes any
   ``dp5k import`` instead, ``--no-real`` leaves the test set out).
4. ``dp5k diagnose`` on the measured pairs (unless ``--no-diagnose``), whose report adds the ``diagnosed`` simulator.
5. ``dp5k study downstream`` (:func:`dp5k_deblur.study.run_downstream`): the Neural DP Simulator trained on the
   measured train split, every simulator (plus ``--simulator LABEL=SPEC``, e.g. the real-calibrated ones of
   ``benchmarks/table2_real.py``), one deblurrer per simulator and seed, both tables on both test sets.

Usage::

    python benchmarks/study_downstream.py OUT [--frames 32] [--measured 96] [--seeds 0,1,2] [--steps 304]
        [--simulator sdirt-diagnosed=diagnosed:T2/diagnose/report.json --simulator sdirt-neural=neural:T2/neural/real_s0.pt]

Synthetic pairs get the sensor noise ``dp5k synthesize`` adds by default. It prints the date, load average and
commit beside the tables, and the wall and CPU time. Everything goes under OUT.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

from dp5k_demo.rgbd import write_rgbd_frames  # noqa: E402  (benchmarks may use the world and the demo)
from dp5k_deblur.config import DeblurTrainConfig
from dp5k_deblur.model import DeblurNetConfig
from dp5k_deblur.study import PEER_SIMULATORS, StudyConfig, run_downstream
from dp5k_studio.dataset import make_dataset
from neural_dp.registry import ModelConfig
from run_info import Stopwatch, machine, markdown_tables, record_result

ROOT = Path(__file__).resolve().parents[1]
SDIRT = ROOT.parent / "shared" / "data" / "sdirt-canon-r6m2"
BATCH = 8
"""Crops per step."""
STEPS_PER_EPOCH = 16


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", type=int, default=32, help="RGBD frames (studio scenes) to synthesize from")
    ap.add_argument("--measured", type=int, default=96, help="measured studio scenes (train / val / test, 75/12.5/12.5 %%)")
    ap.add_argument("--size", default="128x96", help="W x H of frames and measured pairs, px")
    ap.add_argument("--real", type=Path, default=None, help="a dp5k import with train and test splits (default: Sdirt)")
    ap.add_argument("--sdirt", type=Path, default=SDIRT, help="imported with --tile 128x128 when --real is not given")
    ap.add_argument("--no-real", action="store_true", help="only the studio-measured test set")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--steps", type=int, default=304, help="Adam steps of every deblurrer and of the Neural DP Simulator")
    ap.add_argument("--finetune-steps", type=int, default=96, help="Adam steps of the transfer setting")
    ap.add_argument("--few-real-pairs", type=int, default=4)
    ap.add_argument("--effects", default="lr_gain_imbalance=0.5,psf_profile=0.5",
                    help="effects planted in the measured pairs (NAME=STRENGTH,...)")
    ap.add_argument("--no-diagnose", action="store_true", help="leave out the diagnosed simulator")
    ap.add_argument("--simulator", action="append", default=[], metavar="[LABEL=]SPEC", help="another simulator, repeatable")
    ap.add_argument("--no-train-neural", action="store_true", help="leave out the Neural DP Simulator trained in the study")
    ap.add_argument("--channels", type=int, default=12, help="U-Net base channels (DPDNet: 64)")
    ap.add_argument("--levels", type=int, default=3, help="U-Net levels (DPDNet: 4)")
    ap.add_argument("--neural-channels", type=int, default=12, help="Neural DP base channels (the paper: 64)")
    ap.add_argument("--neural-levels", type=int, default=3, help="Neural DP levels (the paper: 4)")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    W, H = (int(v) for v in a.size.lower().split("x"))
    seeds = tuple(int(s) for s in a.seeds.split(","))
    out: Path = a.out
    print(f"# downstream study: {machine()}", flush=True)
    clock = Stopwatch()

    aif = out / "frames_aif"
    if not (aif / "dataset.json").is_file():
        make_dataset(aif, scenes=a.frames, size=(W, H), f_numbers=(2.0,), cameras=(0,), seed=101, noise=False,
                     all_in_focus_sharp=True)
    rgbd = out / "rgbd"
    if not rgbd.is_dir():
        write_rgbd_frames(aif, rgbd, count=a.frames)
    measured = out / "measured"
    effects = [e.strip() for e in a.effects.split(",") if e.strip()]
    if not (measured / "dataset.json").is_file():
        make_dataset(measured, scenes=a.measured, size=(W, H), f_numbers=(2.0, 4.0), cameras=(0,), seed=202, effects=effects)
    real = None if a.no_real else a.real
    if real is None and not a.no_real:
        real = out / "real"
        if not (real / "dataset.json").is_file():
            subprocess.run([sys.executable, "-m", "dp5k_cli", "-q", "import", "sdirt", str(a.sdirt), str(real), "--tile", "128x128"],
                           check=True, cwd=ROOT)
    specs = list(PEER_SIMULATORS)
    if not a.no_diagnose:
        from dp5k_diagnose.run import DiagnoseConfig, auto_fit_pairs, run_diagnose
        from neural_dp.registry import SimulatorSpec

        report = out / "diagnose" / "report.json"
        if not report.is_file():
            rep = run_diagnose(measured, SimulatorSpec(), out / "diagnose", DiagnoseConfig(fit_pairs=auto_fit_pairs(measured)))
            print(f"diagnose: cause {rep['cause']} ({clock})", flush=True)
        specs.append(f"diagnosed:{report}")
    specs += a.simulator

    epochs = max(1, a.steps // STEPS_PER_EPOCH)
    ft_epochs = max(1, a.finetune_steps // STEPS_PER_EPOCH)
    train = DeblurTrainConfig(charbonnier_eps=0.1, model=DeblurNetConfig(base_channels=a.channels, levels=a.levels))
    train = replace(train, data=replace(train.data, crop_px=48, batch_size=BATCH, samples_per_epoch=STEPS_PER_EPOCH * BATCH),
                    optim=replace(train.optim, epochs=epochs, lr=2e-3))
    cfg = StudyConfig(simulators=tuple(specs), train=train, train_neural=not a.no_train_neural,
                      neural_model=replace(ModelConfig(), base_channels=a.neural_channels, levels=a.neural_levels),
                      few_real_pairs=a.few_real_pairs, finetune_epochs=ft_epochs, device=a.device, seeds=seeds)
    study = run_downstream(rgbd, measured, out / "study", cfg, real_pairs=real)
    print(f"\nsettings: {a.frames} RGBD frames and {a.measured} measured scenes (f/2, f/4; effects {', '.join(effects)}) at "
          f"{W} x {H}; real pairs: {real}; U-Net {a.channels} channels x {a.levels} levels; {epochs * STEPS_PER_EPOCH} steps "
          f"of {BATCH} 48-px crops per deblurrer and for the Neural DP Simulator ({a.neural_channels} channels x "
          f"{a.neural_levels} levels), fine-tune {ft_epochs * STEPS_PER_EPOCH} steps on {a.few_real_pairs} pairs; Charbonnier "
          f"eps 0.1; seeds {list(seeds)}; device {a.device}\n")
    print((out / "study" / "tables.md").read_text())
    print("CPU seconds by stage (this process):", {k: round(v) for k, v in study["cpu_s"].items()})
    print(f"{clock}; {machine()}")
    tables, _ = markdown_tables((out / "study" / "tables.md").read_text())
    record_result("downstream-study", "The downstream study: Tables 3 and 4 on studio-measured and real test pairs",
                  *tables[0], tables=[{"title": "", "columns": c, "rows": r} for c, r in tables[1:]],
                  notes=f"Tables in order as in `{out / 'study' / 'tables.md'}`. Cost: {clock}.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
