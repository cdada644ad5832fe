"""The importers by name and the one call that runs an adapter and writes its dataset."""

from __future__ import annotations

import os

from dp5k_common.errors import BadInputError

from .sdirt import sdirt_captures
from .writer import write_imported

IMPORTERS = {"sdirt": sdirt_captures}
"""Adapters by name: ``name -> (src) -> list[Capture]``."""


def import_dataset(kind: str, src: str | os.PathLike[str], out: str | os.PathLike[str], tile: tuple[int, int] | None = None, seed: int = 0) -> dict[str, list[str]]:
    """Run adapter ``kind`` on ``src`` and write the format-v1 dataset to ``out``."""
    if kind not in IMPORTERS:
        raise BadInputError(f"unknown import source {kind!r} (known: {', '.join(IMPORTERS)})")
    return write_imported(out, IMPORTERS[kind](src), tile=tile, seed=seed, source=f"dp5k import {kind}")
