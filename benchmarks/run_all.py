"""Run the speed and memory benchmarks one after another and print their tables (``make bench``).

    python benchmarks/run_all.py [--full] [--only capture,studio,...]

Each benchmark runs as its own process (so one's memory does not count against the next) and prints its own
table; a summary of wall times and exit codes closes the run. ``--full`` gives ``bench_diagnose`` its whole
table instead of the 30-pair target case. The studies (``diagnose_matrix.py``, ``quality_simulators.py``) measure detection and accuracy, not speed, take tens of minutes to
hours, and are run on their own (docs/diagnose.md, docs/simulators.md).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
BENCHES: dict[str, list[str]] = {
    "capture": ["bench_capture.py"],
    "studio": ["bench_studio.py"],
    "process": ["bench_process.py"],
    "simulators": ["bench_simulators.py"],
    "neural": ["bench_neural.py"],
    "diagnose": ["bench_diagnose.py", "--quick"],
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="bench_diagnose's whole table (several minutes more)")
    ap.add_argument("--only", default=",".join(BENCHES), help="comma-separated subset of " + ", ".join(BENCHES))
    a = ap.parse_args()
    names = [n.strip() for n in a.only.split(",") if n.strip()]
    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        print(f"run_all: unknown benchmark(s) {', '.join(unknown)}; choose from {', '.join(BENCHES)}", file=sys.stderr)
        return 2
    rows = []
    for name in names:
        cmd = [sys.executable, str(HERE / BENCHES[name][0]), *BENCHES[name][1:]]
        if name == "diagnose" and a.full:
            cmd = cmd[:2]
        print(f"\n## {name}: {' '.join(Path(c).name for c in cmd[1:])}\n", flush=True)
        t0 = time.perf_counter()
        rc = subprocess.call(cmd, cwd=HERE.parent)
        rows.append((name, time.perf_counter() - t0, rc))
    print("\n| benchmark | wall s | exit |\n|---|---|---|")
    for name, s, rc in rows:
        print(f"| {name} | {s:.0f} | {rc} |")
    return max((rc for _, _, rc in rows), default=0)


if __name__ == "__main__":
    sys.exit(main())
