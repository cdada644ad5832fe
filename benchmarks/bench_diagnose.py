"""Benchmark ``dp5k diagnose`` (base model): wall time against pairs and pixels.

Usage: ``.venv/bin/python benchmarks/bench_diagnose.py [--quick | --large-blur]``. Makes studio datasets
(clean) in a temp folder and prints a table: pairs, image size, the largest |CoC|, the machine's load, time
per stage. The target: 30 pairs of 288 x 192 within 3 minutes on the project's 2-core machine. The row
marked ``*`` is a case again with ``sharp_f_number`` removed from every params.json: diagnose then runs fit
and the base fit twice (f/22 and all-in-focus readings of ``sharp``, docs/diagnose.md).

``--large-blur`` runs issue 22's large-blur cases only: the ``near`` scene (spheres 0.26-0.85 m before a
wall) at 250 x 170, 2 cameras x 5 f-numbers (10 pairs, discs up to about 87 px), without
``sharp_f_number`` (target: under 3 minutes), and a 24-pair 256 x 170 set of random scenes (target: under
1 minute).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

import torch

from run_info import record_result

os.environ.setdefault("DP5K_PROGRESS", "0")


def main() -> None:
    from dp5k_studio.dataset import make_dataset
    from dp5k_diagnose.run import diagnose_base

    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="only the 30-pair 288x192 target case")
    ap.add_argument("--large-blur", action="store_true", help="only issue 22's large-blur cases")
    args = ap.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    print(f"{datetime.datetime.now():%Y-%m-%d %H:%M}, commit {commit}, {os.cpu_count()} CPUs")
    # (scenes, cameras, f-numbers, size, strip sharp_f_number): pairs = scenes * cameras * f-numbers
    cases = [(3, 2, (1.8, 2.8, 4.0, 5.6, 2.0), (288, 192), True)]
    if args.large_blur:
        cases = [(["near"], 2, (1.8, 2.0, 2.8, 4.0, 5.6), (250, 170), True), (4, 2, (1.8, 2.0, 2.8), (256, 170), False)]
    elif not args.quick:
        cases += [
            (3, 2, (1.8, 2.8), (288, 192), False),
            (6, 2, (1.8, 2.8, 4.0, 5.6, 2.0), (288, 192), False),
            (3, 2, (1.8, 2.8, 4.0, 5.6, 2.0), (144, 96), False),
            (3, 2, (1.8, 2.8, 4.0, 5.6, 2.0), (576, 384), False),
        ]
    print(f"torch threads {torch.get_num_threads()}; 'cpu s' is this process's CPU time for the diagnosis (on a shared machine the "
          "wall seconds wait for a core, the CPU seconds do not)")
    print(f"{'pairs':>5} {'size':>9} {'max|CoC|':>8} {'cpu load':>8} {'read':>6} {'fit':>6} {'atlas':>6} {'sig':>6} {'name':>6} {'gain':>6} {'total s':>8} {'cpu s':>7}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (scenes, cams, fns, size, strip) in enumerate(cases):
            root = Path(tmp) / f"ds{i}"
            make_dataset(root, scenes=scenes, size=size, f_numbers=fns, cameras=tuple(range(cams)), seed=i)
            n = (len(scenes) if isinstance(scenes, list) else scenes) * cams * len(fns)
            coc = _max_abs_coc(root)
            t0, c0 = time.perf_counter(), time.process_time()
            tt = diagnose_base(root).timings_s
            print(f"{n:5d} {size[0]:>4}x{size[1]:<4} {coc:8.1f} {os.getloadavg()[0]:8.1f} {tt['read']:6.1f} {tt['fit_base']:6.1f} "
                  f"{tt['atlas']:6.1f} {tt['signatures']:6.1f} {tt['name']:6.1f} {tt['gain']:6.1f} {time.perf_counter() - t0:8.1f} {time.process_time() - c0:7.1f}", flush=True)
            rows.append([n, f"{size[0]} x {size[1]}", f"{coc:.1f}", f"{os.getloadavg()[0]:.1f}", *(f"{tt[k]:.1f}" for k in ("read", "fit_base", "atlas", "signatures", "name", "gain")),
                         f"{time.perf_counter() - t0:.1f}", f"{time.process_time() - c0:.1f}"])
            if strip:
                for f in (root / "pairs").glob("*/params.json"):
                    obj = json.loads(f.read_text())
                    obj.pop("sharp_f_number", None)
                    f.write_text(json.dumps(obj))
                t0, c0 = time.perf_counter(), time.process_time()
                tt = diagnose_base(root).timings_s
                print(f"{n:5d} {size[0]:>4}x{size[1]:<3}* {coc:8.1f} {os.getloadavg()[0]:8.1f} {tt['read']:6.1f} {tt['fit_base']:6.1f} "
                      f"{tt['atlas']:6.1f} {tt['signatures']:6.1f} {tt['name']:6.1f} {tt['gain']:6.1f} {time.perf_counter() - t0:8.1f} {time.process_time() - c0:7.1f}", flush=True)
                rows.append([n, f"{size[0]} x {size[1]} *", f"{coc:.1f}", f"{os.getloadavg()[0]:.1f}", *(f"{tt[k]:.1f}" for k in ("read", "fit_base", "atlas", "signatures", "name", "gain")),
                             f"{time.perf_counter() - t0:.1f}", f"{time.process_time() - c0:.1f}"])
    mode = "-large-blur" if args.large_blur else "-quick" if args.quick else ""
    record_result(f"speed-diagnose{mode}", f"Diagnose (base model): seconds per stage{' (issue 22 large-blur cases)' if args.large_blur else ''}",
                  ["pairs", "size", "max abs(CoC) px", "load (1 min)", "read s", "fit s", "measured atlas s", "simulator atlas + signatures s", "naming s", "gain s", "total s", "CPU s"], rows,
                  notes=f"torch threads {torch.get_num_threads()}. * = the same set with `sharp_f_number` removed (the base model "
                        "is fitted under both readings of `sharp`). Targets: 30 pairs of 288 x 192 within 3 minutes; large blur: the `near` "
                        "set without `sharp_f_number` under 3 minutes, a 24-pair 256 x 170 set under 1 minute.")


def _max_abs_coc(root: Path) -> float:
    """Largest |CoC| (px) over a dataset's pairs (their coc.tif)."""
    import numpy as np
    import tifffile

    return max(float(np.nanmax(np.abs(tifffile.imread(f)))) for f in (root / "pairs").glob("*/coc.tif"))


if __name__ == "__main__":
    main()
