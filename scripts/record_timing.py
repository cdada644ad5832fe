"""Time a command and record it in the results store (docs/results.md), e.g. the README's two commands.

Usage::

    python scripts/record_timing.py NAME [--title TEXT] [--notes TEXT] -- COMMAND [ARG ...]
    python scripts/record_timing.py test -- make test
    python scripts/record_timing.py demo -- make demo        # into a fresh demo-out/ for a first-run figure

Runs COMMAND (its output passes through), measures its wall time, the CPU time of it and its children, and the
machine's load before and after, and writes ``benchmarks/results/make-NAME/latest.json`` (replacing the run
before) with the exit code. Then ``python scripts/gen_results.py`` puts it in docs/results.md. Exits with the
command's exit code; a failed command is recorded too (its exit code says so).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from run_info import record_result  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--" not in argv:
        print("record_timing: usage: record_timing.py NAME [--title T] [--notes N] -- COMMAND ...", file=sys.stderr)
        return 2
    split = argv.index("--")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name", help="the result's name: make-NAME in the store (e.g. test, demo)")
    ap.add_argument("--title", default=None)
    ap.add_argument("--notes", default="")
    a = ap.parse_args(argv[:split])
    command = argv[split + 1:]
    if not command:
        print("record_timing: no command after --", file=sys.stderr)
        return 2
    load0 = os.getloadavg()
    kids0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    rc = subprocess.call(command)
    wall = time.perf_counter() - t0
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (kids.ru_utime - kids0.ru_utime) + (kids.ru_stime - kids0.ru_stime)
    load1 = os.getloadavg()
    text = " ".join(command)
    record_result(f"make-{a.name}", a.title or f"`{text}`", ["command", "wall", "CPU", "exit code", "load before / after (1 min)"],
                  [[f"`{text}`", f"{wall / 60:.1f} min ({wall:.0f} s)", f"{cpu / 60:.1f} CPU-min", str(rc),
                    f"{load0[0]:.1f} / {load1[0]:.1f}"]],
                  command=f"python scripts/record_timing.py {a.name} -- {text}", notes=a.notes,
                  load=[round(v, 2) for v in load0])
    return rc


if __name__ == "__main__":
    sys.exit(main())
