"""Which software produced a result: dp5k's version and the numerical libraries its numbers depend on.

Diagnose's screens and fits are deterministic for one environment, but not across library releases
(``pyproject.toml`` sets lower bounds only): two quick matrices a day apart named different causes on two
sets with the same code and new wheels. Every report and benchmark row therefore carries this block.
"""

from __future__ import annotations

import platform
from importlib import metadata

from . import __version__

__all__ = ["NUMERICAL_PACKAGES", "software_versions", "software_line"]

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
