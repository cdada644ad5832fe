"""What every long benchmark run prints beside its tables: when, at which commit, at what load, and its cost in wall
and CPU seconds (this process and the commands it ran, e.g. ``dp5k import`` and ``dp5k diagnose``)."""

from __future__ import annotations

import datetime
import os
import resource
import subprocess
import time
from pathlib import Path


def machine() -> str:
    """``date, commit, load average 1 / 5 / 15 on N cores``."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip() or "unknown"
    load = os.getloadavg()
    return (f"{datetime.datetime.now().isoformat(timespec='seconds')}, commit {commit}, load average "
            f"{load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} on {os.cpu_count()} cores")


def cpu_seconds() -> float:
    """User + system CPU seconds of this process (every thread) and of its finished child processes."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


class Stopwatch:
    """Wall and CPU seconds since it was made."""

    def __init__(self) -> None:
        self.wall0, self.cpu0 = time.perf_counter(), cpu_seconds()

    def __str__(self) -> str:
        return f"{(time.perf_counter() - self.wall0) / 60:.1f} min wall, {(cpu_seconds() - self.cpu0) / 60:.1f} CPU-min"
