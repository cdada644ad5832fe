"""The downstream study on studio data (the run docs/deblur.md reports): Tables 3 and 4 of the paper for this data.

Steps:

1. RGBD frames: studio scenes rendered with their all-in-focus radiance as ``sharp`` (``make_dataset(...,
   all_in_focus_sharp=True)``), written as ``dp5k synthesize`` frames (image, depth, intrinsics): the stand-in
   for Hypersim, which cannot be fetched here.
2. "Measured" pairs: other studio scenes with planted physical effects and sensor noise (``--effects``), f/22
   ``sharp`` as in a capture: the stand-in for DP5K's test split.
3. ``dp5k diagnose`` on the measured pairs (unless ``--no-diagnose``), whose report adds the ``diagnosed`` simulator.
4. ``dp5k study downstream`` (:func:`dp5k_deblur.study.run_downstream`): every simulator, one deblurrer each,
   Tables 3 and 4, the figure.

Usage::

    python benchmarks/study_downstream.py OUT [--frames 12] [--measured 24] [--size 128x96] [--steps 300]

It prints the date, load average and commit beside the tables and the wall time. Everything goes under OUT.
"""

from __future__ import annotations

import argparse
import datetime
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

from dp5k_demo.rgbd import write_rgbd_frames  # noqa: E402  (benchmarks may use the world and the demo)
from dp5k_deblur.config import DeblurTrainConfig
from dp5k_deblur.model import DeblurNetConfig
from dp5k_deblur.study import PEER_SIMULATORS, StudyConfig, run_downstream
from dp5k_studio.dataset import make_dataset

BATCH = 8
"""Crops per step."""


def machine() -> str:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip() or "unknown"
    load = os.getloadavg()
    return (f"{datetime.datetime.now().isoformat(timespec='seconds')}, commit {commit}, load average "
            f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} on {os.cpu_count()} cores")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--frames", type=int, default=12, help="RGBD frames (studio scenes) to synthesize from")
    ap.add_argument("--measured", type=int, default=24, help="measured studio scenes (train / val / test)")
    ap.add_argument("--size", default="128x96", help="W x H of frames and measured pairs, px")
    ap.add_argument("--steps", type=int, default=300, help="Adam steps of every deblurrer (pre-training budget)")
    ap.add_argument("--finetune-steps", type=int, default=100, help="Adam steps of the transfer setting")
    ap.add_argument("--few-real-pairs", type=int, default=4)
    ap.add_argument("--effects", default="lr_gain_imbalance=0.5,psf_profile=0.5",
                    help="effects planted in the measured pairs (NAME=STRENGTH,...)")
    ap.add_argument("--no-diagnose", action="store_true", help="leave out the diagnosed simulator")
    ap.add_argument("--neural-checkpoint", default=None, help="adds the Neural DP Simulator")
    ap.add_argument("--channels", type=int, default=12, help="U-Net base channels (DPDNet: 64)")
    ap.add_argument("--levels", type=int, default=3, help="U-Net levels (DPDNet: 4)")
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    W, H = (int(v) for v in a.size.lower().split("x"))
    out: Path = a.out
    print(f"# downstream study: {machine()}", flush=True)
    t_start = time.perf_counter()

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
    report = None
    if not a.no_diagnose:
        from dp5k_diagnose.run import run_diagnose
        from neural_dp.registry import SimulatorSpec

        report = out / "diagnose" / "report.json"
        if not report.is_file():
            rep = run_diagnose(measured, SimulatorSpec(), out / "diagnose")
            print(f"diagnose: cause {rep['cause']} ({time.perf_counter() - t_start:.0f} s so far)", flush=True)

    pairs_per_epoch = 16 * BATCH  # 16 steps per epoch
    train = DeblurTrainConfig(
        charbonnier_eps=0.1, model=DeblurNetConfig(base_channels=a.channels, levels=a.levels),
    )
    train = replace(train, data=replace(train.data, crop_px=48, batch_size=BATCH, samples_per_epoch=pairs_per_epoch),
                    optim=replace(train.optim, epochs=max(1, a.steps // 16), lr=2e-3))
    specs = PEER_SIMULATORS + ((f"neural:{a.neural_checkpoint}",) if a.neural_checkpoint else ()) \
        + ((f"diagnosed:{report}",) if report is not None else ())
    cfg = StudyConfig(simulators=specs, train=train,
                      few_real_pairs=a.few_real_pairs, finetune_epochs=max(1, a.finetune_steps // 16), device=a.device)
    run_downstream(rgbd, measured, out / "study", cfg)
    wall = time.perf_counter() - t_start
    print(f"\nsettings: {a.frames} RGBD frames and {a.measured} measured scenes (f/2, f/4; effects {', '.join(effects)}) at "
          f"{W} x {H}; U-Net {a.channels} channels x {a.levels} levels; {max(1, a.steps // 16) * 16} steps of {BATCH} "
          f"48-px crops per deblurrer, fine-tune {max(1, a.finetune_steps // 16) * 16} steps on {a.few_real_pairs} pairs; "
          f"Charbonnier eps 0.1; seed 0; device {a.device}\n")
    for key in ("table3", "table4"):
        print((out / "study" / f"{key}.md").read_text())
    print(f"wall time {wall / 60:.1f} min; {machine()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
