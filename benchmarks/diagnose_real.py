"""``dp5k diagnose`` on real DP data: the Sdirt flat targets (Canon EOS R6 Mark II + RF50 at f/4, focus 1 m), measured
the way a user works: ``dp5k import sdirt SRC --out OUT/real --tile WxH``, then ``dp5k diagnose OUT/real --out
OUT/diagnose``, then ``dp5k evaluate OUT/real --split test`` of the peers, the base model, the diagnosed model and the
camera's own measured kernels (``measured:OUT/diagnose/atlas.npz``).

The two photos (a plane 0.6 m away, in front of focus, and one 1.5 m away, behind it) are imported as two sources:
one is train, the other test, so the atlas of every tile pools both sides of focus while the named causes must gain
on the photo no fit saw. Prints and records (``diagnose-sdirt``): the named causes with their signatures and held-out
gains, every effect's signature, the atlas's measured cells, and the evaluation's table.

    python benchmarks/diagnose_real.py OUT [--sdirt SRC] [--tile 192x128]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from run_info import Stopwatch, machine, record_result

ROOT = Path(__file__).resolve().parents[1]
SDIRT = ROOT.parent / "shared" / "data" / "sdirt-canon-r6m2"


def dp5k(*args: str) -> None:
    """Run a dp5k command as a user would (the CLI of this checkout), failing loudly."""
    subprocess.run([sys.executable, "-m", "dp5k_cli", "-q", *args], check=True, cwd=ROOT)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--sdirt", type=Path, default=SDIRT, help="Sdirt DP119 or its real_sample_set (dp5k import sdirt SRC)")
    ap.add_argument("--tile", default="192x128", help="dp5k import sdirt --tile")
    a = ap.parse_args(argv)
    if not a.sdirt.is_dir():
        print(f"diagnose_real: no Sdirt data at {a.sdirt}", file=sys.stderr)
        return 2
    watch = Stopwatch()
    real, diag, ev = a.out / "real", a.out / "diagnose", a.out / "evaluate"
    if not (real / "dataset.json").is_file():
        dp5k("import", "sdirt", str(a.sdirt), "--out", str(real), "--tile", a.tile)
    dp5k("diagnose", str(real), "--out", str(diag))
    rep = json.loads((diag / "report.json").read_text())
    sims = ["disk", "butterworth", "raytrace", "base", f"diagnosed:{diag / 'report.json'}", f"measured:{diag / 'atlas.npz'}"]
    dp5k("evaluate", str(real), "--split", "test", "--out", str(ev), *(x for s in sims for x in ("--simulator", s)))
    metrics = json.loads((ev / "metrics.json").read_text())
    g = rep["gain"]
    rows = [[c["name"], f"{c['gain_db']:+.2f} [{c['gain_ci_db'][0]:+.2f}, {c['gain_ci_db'][1]:+.2f}]", c["explanation"]] for c in rep["causes"]]
    sig_rows = []
    for e, s in rep["signatures"].items():
        if s["unmeasured"]:
            sig_rows.append([e, "not measured: " + s["unmeasured"], "-", "-"])
            continue
        for v in s["values"]:
            lo, hi = v["interval95"]
            sig_rows.append([e, f"{v['name']} {v['value']:+.4g} {v['unit']}", f"[{lo:+.4g}, {hi:+.4g}]", "differs" if s["differs"] else "-"])
    print(machine())
    print(f"causes: {[c['name'] for c in rep['causes']]}; held-out gain {g['psnr_after'] - g['psnr_before']:+.2f} dB "
          f"[{g['psnr_gain_ci95'][0]:+.2f}, {g['psnr_gain_ci95'][1]:+.2f}] on {g['n_pairs']} test tiles; atlas "
          f"{rep['atlas']['measured']} of {rep['atlas']['cells']} cells measured; {watch}")
    for r in rows:
        print("  ", *r)
    for r in sig_rows:
        print("  ", *r)
    for name, m in metrics["means"].items():
        print(f"   evaluate {name}: PSNR {m['psnr']:.2f} SSIM {m['ssim']:.4f} MAE {m['mae']:.4f}")
    record_result("diagnose-sdirt", "Diagnose on real DP data (Sdirt, Canon EOS R6 II, flat targets at 0.6 and 1.5 m, f/4)",
                  ["cause", "held-out gain given the others dB [95 %]", "what it is"], rows or [["none", "-", "-"]],
                  command=" ".join(["python", "benchmarks/diagnose_real.py", *(argv or sys.argv[1:])]),
                  notes=f"Whole gain on the test photo's tiles: {g['psnr_before']:.2f} -> {g['psnr_after']:.2f} dB "
                        f"(95 % [{g['psnr_gain_ci95'][0]:+.2f}, {g['psnr_gain_ci95'][1]:+.2f}]). Atlas: {rep['atlas']['measured']} of "
                        f"{rep['atlas']['cells']} cells measured on {rep['atlas']['pairs']} tiles. Signatures: "
                        + "; ".join(f"{r[0]} {r[1]} {r[2]} {r[3]}" for r in sig_rows)
                        + ". Evaluation on the test photo (masked PSNR, each simulator): "
                        + "; ".join(f"{k} {v:.2f}" for k, v in _psnr(metrics).items()) + f". {watch}.")
    return 0


def _psnr(metrics: dict) -> dict[str, float]:
    """simulator -> mean masked PSNR of ``dp5k evaluate``'s metrics.json."""
    return {name: float(m["psnr"]) for name, m in metrics["means"].items()}


if __name__ == "__main__":
    sys.exit(main())
