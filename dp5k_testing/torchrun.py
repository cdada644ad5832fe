"""Run a ``dp5k`` command under ``torchrun`` on this machine's CPU: how the tests and benchmarks check sharding.

``torchrun --standalone --nproc_per_node N -m dp5k_cli -q ARGS...`` (``python -m torch.distributed.run``, so
the interpreter running the tests is the one the ranks use), one intra-op thread per rank and no progress bars.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_torchrun(args: Sequence[str], nproc: int = 2, timeout_s: float = 240.0, check: bool = False) -> subprocess.CompletedProcess[str]:
    """Run ``dp5k ARGS`` as ``nproc`` torchrun ranks from the repository root; stdout/stderr captured as text.

    The ranks import the same dp5k as this process: the repository root is put first on their ``PYTHONPATH``.
    """
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}",
           "-m", "dp5k_cli", "-q", *map(str, args)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "DP5K_PROGRESS": "0",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout_s, check=check)
