"""Every cause, in order: diagnose on data with two planted effects at once, from the studio or from
``dp5k_testing/foreign_dp.py`` (a renderer that shares no code with dp5k).

For each pair of effects it writes a dataset, runs diagnose (base model, the CLI's fit-pair rule) and prints
one row: planted, the causes named in order with the held-out PSNR gain each adds given the other causes and its step gain (95 % CI over pairs) and the
fitted parameters that compare with the planted ones, the cumulative gain, the time, and beside every row
the date, the machine's load and the git commit. The floor each step is measured against is the model of the
steps before it, on the same held-out pairs (step 1: the fitted base model).

    python benchmarks/multi_cause_sweep.py [--renderer studio|foreign] [--cases a+b,c+d,...] [--seed N]
                                           [--size 160x96] [--scenes 13] [--strength 1] [--out DIR]
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dp5k_diagnose.run import DiagnoseConfig, auto_fit_pairs, diagnose_base
from run_info import options_suffix, recording

DEFAULT_CASES = ("lr_gain_imbalance+disparity_scale", "psf_profile+focus_offset", "disparity_scale+psf_profile",
                 "field_varying_psf+misregistration", "none")
KEY_PARAMS = {"lr_gain_imbalance": ("lr_ratio_center",), "disparity_scale": ("disparity_scale",), "focus_offset": ("focus_factor",),
              "psf_profile": ("rim_gain",), "field_varying_psf": ("edge_leak", "coc_growth_at_corner"), "misregistration": ("left_dx_px", "left_dy_px"),
              "front_back_asymmetry": ("front_size_factor", "back_rim_gain"), "chromatic_defocus": ("focal_shift_r_mm", "focal_shift_b_mm"),
              "noise": ("shot_var", "read_sigma")}


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
                              cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def write(renderer: str, root: Path, case: str, strength: float, size: tuple[int, int], scenes: int, seed: int) -> None:
    if renderer == "studio":
        import dp5k_studio.dataset as studio

        effects = {} if case == "none" else {e: strength for e in case.split("+")}
        studio.make_dataset(root, scenes=scenes, effects=effects, size=size, f_numbers=(1.8, 2.8), cameras=(0, 1), seed=seed)
    else:
        from dp5k_testing.foreign_dp import write_dataset

        write_dataset(root, case, strength, scenes=scenes, size=size, seed=seed)


def step_text(c: dict) -> str:
    keys = KEY_PARAMS.get(c["name"], ())
    iv = c.get("param_intervals", {})
    par = ", ".join(f"{k} {c['params'][k]:.3g}" + (f" [{iv[k][0]:.3g}, {iv[k][1]:.3g}]" if k in iv else "") for k in keys if k in c["params"])
    lo, hi = c["gain_ci_db"]
    slo, shi = c["step_gain_ci_db"]
    return (f"`{c['name']}` {c['gain_db']:+.2f} [{lo:+.2f}, {hi:+.2f}] dB given the others, step {c['step_gain_db']:+.2f} "
            f"[{slo:+.2f}, {shi:+.2f}] ({par})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--renderer", default="studio", choices=["studio", "foreign"])
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--size", default=None, help="WxH (default: 160x96 studio, 192x128 foreign)")
    ap.add_argument("--scenes", type=int, default=None, help="default: 13 studio, 12 foreign")
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=None, help="keep the datasets and reports here")
    a = ap.parse_args()
    W, H = (int(v) for v in (a.size or ("160x96" if a.renderer == "studio" else "192x128")).split("x"))
    scenes = a.scenes or (13 if a.renderer == "studio" else 12)
    work = a.out or Path(tempfile.mkdtemp(prefix="dp5k-multi-"))
    os.environ.setdefault("DP5K_PROGRESS", "0")
    print(f"{a.renderer}, {W} x {H}, {scenes} scenes, seed {a.seed}, strength {a.strength:g}")
    print("| planted | named in order: gain given the others and step gain [95 % CI] (fitted) | cumulative dB | s | date, load (1 min), commit |")
    print("|---|---|---|---|---|")
    for case in a.cases.split(","):
        root = work / f"{a.renderer}_{case}_{W}x{H}_seed{a.seed}"
        if root.exists():
            shutil.rmtree(root)
        write(a.renderer, root, case, a.strength, (W, H), scenes, a.seed)
        t0 = time.perf_counter()
        rep = diagnose_base(root, DiagnoseConfig(fit_pairs=auto_fit_pairs(root), seed=0)).to_json()
        dt = time.perf_counter() - t0
        named = "; ".join(step_text(c) for c in rep["causes"]) or "`none`"
        cum = rep["causes"][-1]["cumulative_gain_db"] if rep["causes"] else 0.0
        stamp = f"{datetime.datetime.now():%Y-%m-%d %H:%M}, {os.getloadavg()[0]:.1f}, {commit()}"
        print(f"| {case} | {named} | {cum:+.2f} | {dt:.0f} | {stamp} |", flush=True)
    if a.out is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    with recording(f"diagnose-multi-cause{options_suffix(sys.argv[1:])}", "Diagnose with two planted effects: every cause in order"):
        main()
