"""Progress bars for long work (tqdm on stderr), silenced by ``dp5k -q``.

Library code wraps long loops in :func:`progress`; the CLI decides whether bars are shown.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")
_enabled = os.environ.get("DP5K_PROGRESS", "1") != "0"


def set_progress_enabled(enabled: bool) -> None:
    """Show (True) or hide (False) every progress bar created from now on."""
    global _enabled
    _enabled = enabled


def progress(iterable: Iterable[T] | None = None, *, desc: str = "", total: int | None = None, unit: str = "it", **kw: Any) -> Any:
    """A tqdm bar over ``iterable`` (or a manual bar when ``iterable`` is None), on stderr.

    Args:
        iterable: what to iterate; None for a manual bar (call ``.update(n)``).
        desc: short label shown before the bar.
        total: number of items when ``len(iterable)`` is unknown.
        unit: the item's name ("scene", "pair", "step").
    """
    return tqdm(iterable, desc=desc, total=total, unit=unit, disable=not _enabled, dynamic_ncols=True, leave=False, **kw)
