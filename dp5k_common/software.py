"""Which software produced a result: dp5k's version, its git commit, the command, and the numerical libraries its
numbers depend on.

Diagnose's screens and fits are deterministic for one environment, but not across library releases
(``pyproject.toml`` sets lower bounds only): two quick matrices a day apart named different causes on two
sets with the same code and new wheels. Every report and benchmark row therefore carries this block.

Every ``dataset.json``, ``metrics.json`` and ``report.json`` dp5k writes carries :func:`provenance` under the key
``"provenance"``: which dp5k (version, commit, uncommitted changes) and which command wrote it.
"""

from __future__ import annotations

import functools
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any

from . import __version__

__all__ = ["NUMERICAL_PACKAGES", "PROVENANCE_KEY", "COMMAND_META_KEY", "software_versions", "software_line", "git_state",
           "provenance"]

PROVENANCE_KEY = "provenance"
"""The key under which result files hold :func:`provenance`."""
COMMAND_META_KEY = "dp5k.command"
"""``click.Context.meta`` key where the ``dp5k`` command line puts its arguments (``["dp5k", "process", ...]``)."""
REPO_ROOT = Path(__file__).resolve().parents[1]
"""The folder dp5k's code runs from (holding ``dp5k_cli.py``): a git checkout, or site-packages."""

NUMERICAL_PACKAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("numpy", ("numpy",)),
    ("scipy", ("scipy",)),
    ("torch", ("torch",)),
    ("opencv", ("opencv-contrib-python", "opencv-contrib-python-headless", "opencv-python", "opencv-python-headless")),
)
"""(short name, distributions that provide it, first installed one wins)."""


def _installed(dists: tuple[str, ...]) -> str | None:
    for d in dists:
        try:
            return metadata.version(d)
        except metadata.PackageNotFoundError:
            continue
    return None


def software_versions() -> dict[str, str]:
    """``{"dp5k": ..., "python": ..., "numpy": ..., ...}``: versions as installed (``"absent"`` when not).

    >>> v = software_versions()
    >>> sorted(v) == sorted(["dp5k", "python"] + [n for n, _ in NUMERICAL_PACKAGES])
    True
    """
    out = {"dp5k": __version__, "python": platform.python_version()}
    for name, dists in NUMERICAL_PACKAGES:
        out[name] = _installed(dists) or "absent"
    return out


def software_line(versions: dict[str, str]) -> str:
    """One line for a table's header: ``numpy 2.4.6, scipy 1.17.1, ...`` in the dict's order.

    >>> software_line({"numpy": "2.4.6", "torch": "2.13.0+cpu"})
    'numpy 2.4.6, torch 2.13.0+cpu'
    """
    return ", ".join(f"{k} {v}" for k, v in versions.items())



@functools.lru_cache(maxsize=4)
def git_state(root: Path = REPO_ROOT) -> tuple[str | None, bool | None]:
    """``(commit, dirty)`` of the git checkout dp5k runs from: ``git rev-parse HEAD`` in ``root`` and whether tracked
    files differ from it; ``(None, None)`` when ``root`` is not the top of a git checkout (an installed package) or
    git is missing. Cached per process."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=True,
                              timeout=10).stdout.strip()

    try:
        if Path(git("rev-parse", "--show-toplevel")).resolve() != Path(root).resolve():
            return None, None  # an install inside some other repository
        commit = git("rev-parse", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return None, None
    return commit, dirty


def _command() -> list[str]:
    """The command line that runs: the ``dp5k`` arguments when under the CLI (also in-process, as the tests and the
    demo run it), else ``sys.argv``."""
    try:
        import click

        ctx = click.get_current_context(silent=True)
    except ImportError:  # pragma: no cover - click is a dependency
        ctx = None
    if ctx is not None and COMMAND_META_KEY in ctx.meta:
        return list(ctx.meta[COMMAND_META_KEY])
    return list(sys.argv)


def provenance() -> dict[str, Any]:
    """What wrote a result: ``{"dp5k": version, "commit": git HEAD or None, "dirty": tracked files changed (None
    outside a checkout), "command": [argv...]}``.

    >>> p = provenance()
    >>> sorted(p), p["dp5k"] == __version__, isinstance(p["command"], list)
    (['command', 'commit', 'dirty', 'dp5k'], True, True)
    """
    commit, dirty = git_state()
    return {"dp5k": __version__, "commit": commit, "dirty": dirty, "command": _command()}
