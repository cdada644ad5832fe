"""Benchmark ``dp5k diagnose`` (base model): wall time against pairs and pixels.

Usage: ``.venv/bin/python benchmarks/bench_diagnose.py [--quick]``. Makes studio datasets (clean) in a temp
folder and prints a table: pairs, image size, time per stage. The target: 30 pairs of 288 x 192 within
3 minutes on the project's 2-core machine. The row marked ``*`` is the target case again with
``sharp_f_number`` removed from every params.json: diagnose then runs fit and detection twice (f/22 and
all-in-focus readings of ``sharp``, docs/diagnose.md).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("DP5K_PROGRESS", "0")


def main() -> None:
    from dp5k_studio.dataset import make_dataset
    from dp5k_diagnose.run import diagnose_base

    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="only the 30-pair 288x192 target case")
    args = ap.parse_args()
    # (scenes, cameras, f-numbers, size): pairs = scenes * cameras * f-numbers
    cases = [(3, 2, (1.8, 2.8, 4.0, 5.6, 2.0), (288, 192))]
    if not args.quick:
        cases += [
            (3, 2, (1.8, 2.8), (288, 192)),
            (6, 2, (1.8, 2.8, 4.0, 5.6, 2.0), (288, 192)),
            (3, 2, (1.8, 2.8, 4.0, 5.6, 2.0), (144, 96)),
            (3, 2, (1.8, 2.8, 4.0, 5.6, 2.0), (576, 384)),
        ]
    print(f"{'pairs':>5} {'size':>9} {'load':>6} {'fit':>6} {'detect':>7} {'gain':>6} {'total s':>8}")
    with tempfile.TemporaryDirectory() as tmp:
        for i, (scenes, cams, fns, size) in enumerate(cases):
            root = Path(tmp) / f"ds{i}"
            make_dataset(root, scenes=scenes, size=size, f_numbers=fns, cameras=tuple(range(cams)), seed=i)
            t0 = time.perf_counter()
            d = diagnose_base(root)
            tt = d.timings_s
            n = scenes * cams * len(fns)
            print(f"{n:5d} {size[0]:>4}x{size[1]:<4} {tt['load']:6.1f} {tt['fit_base']:6.1f} {tt['detect']:7.1f} {tt['gain']:6.1f} {time.perf_counter() - t0:8.1f}")
            if i == 0:
                for f in (root / "pairs").glob("*/params.json"):
                    obj = json.loads(f.read_text())
                    obj.pop("sharp_f_number", None)
                    f.write_text(json.dumps(obj))
                t0 = time.perf_counter()
                tt = diagnose_base(root).timings_s
                print(f"{n:5d} {size[0]:>4}x{size[1]:<3}* {tt['load']:6.1f} {tt['fit_base']:6.1f} {tt['detect']:7.1f} {tt['gain']:6.1f} {time.perf_counter() - t0:8.1f}")


if __name__ == "__main__":
    main()
