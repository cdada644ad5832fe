"""Diagnose on data from another renderer: every effect of the vocabulary planted by ``dp5k_testing/foreign_dp.py``.

The studio and the base model were built side by side; this renderer shares no code with either (a per-pixel
scatter without occlusion, its own scenes, textures, optics and effect formulas), so this is the check closest
to the independent suite that plants effects in data dp5k has never seen. For each case it writes a dataset,
runs ``dp5k diagnose`` (base model, CLI defaults) and prints one row: planted, named, the leading findings,
the held-out PSNR gain with its 95 % CI, and the time.

    python benchmarks/foreign_sweep.py [--size 192x128] [--scenes 12] [--seed 0] [--strength 1]
                                       [--effects a,b,...] [--unstated-sharp] [--out DIR]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path


from dp5k_common.effects import EFFECT_NAMES
from dp5k_diagnose.run import DiagnoseConfig, run_diagnose
from dp5k_testing.foreign_dp import write_dataset
from neural_dp.registry import SimulatorSpec
from run_info import options_suffix, recording


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="192x128")
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--strength", type=float, default=1.0)
    ap.add_argument("--effects", default="none," + ",".join(EFFECT_NAMES))
    ap.add_argument("--f-numbers", default="2,4")
    ap.add_argument("--unstated-sharp", action="store_true", help="params.json does not state sharp_f_number")
    ap.add_argument("--sharp-f-number", type=float, default=0.0, help="the f-number sharp is rendered at (0 = all-in-focus)")
    ap.add_argument("--sampling", default="box", choices=["box", "tent"], help="how PSFs become pixel weights (dp5k_testing/foreign_dp.half_kernel)")
    ap.add_argument("--out", type=Path, default=None, help="keep the datasets and reports here")
    a = ap.parse_args()
    W, H = (int(v) for v in a.size.split("x"))
    work = a.out or Path(tempfile.mkdtemp(prefix="dp5k-foreign-"))
    print(f"| planted | named | findings (effect size, p) | gain dB [95 % CI] | s |")
    print("|---|---|---|---|---|")
    for eff in a.effects.split(","):
        ds = work / f"{eff}_s{a.strength:g}_{W}x{H}_seed{a.seed}_{a.sampling}"
        if ds.exists():
            shutil.rmtree(ds)
        write_dataset(ds, eff, a.strength, scenes=a.scenes, size=(W, H), seed=a.seed,
                      f_numbers=tuple(float(v) for v in a.f_numbers.split(",")),
                      sharp_f_number=a.sharp_f_number, state_sharp_f_number=not a.unstated_sharp, sampling=a.sampling)
        t0 = time.perf_counter()
        res = run_diagnose(ds, SimulatorSpec(), ds / "diagnose", DiagnoseConfig(fit_pairs=6))
        dt = time.perf_counter() - t0
        top = ", ".join(f"{f['effect']} {f['effect_size']:.2f} ({f['p_value']:.1g})" for f in res["findings"][:3])
        g = res["gain"]
        lo, hi = g["psnr_gain_ci95"]
        ok = res["cause"] == eff
        print(f"| {eff} | {'**' if not ok else ''}{res['cause']}{'**' if not ok else ''} | {top} | "
              f"{g['psnr_after'] - g['psnr_before']:+.2f} [{lo:+.2f}, {hi:+.2f}] | {dt:.0f} |", flush=True)
    if a.out is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    with recording(f"diagnose-foreign-sweep{options_suffix(sys.argv[1:])}", "Diagnose on another renderer's data (foreign_dp), every effect"):
        main()
