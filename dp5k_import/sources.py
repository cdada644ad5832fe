"""The importers by name and the one call that runs an adapter and writes its dataset."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dp5k_common.errors import BadInputError
from dp5k_common.outdir import check_out_dir

from .capture import SceneSource
from .dp5k_release import dp5k_sources
from .dpdd import dpdd_sources
from .generic import generic_sources
from .plan import read_previous
from .sdirt import sdirt_sources
from .writer import write_imported


@dataclass(frozen=True)
class Importer:
    """One source layout.

    Attributes:
        sources: ``(src, **options) -> scenes``.
        tile: default tiling (W, H) of its frames, None = whole frames.
        options: the keyword options ``sources`` accepts (the CLI passes only these).
    """

    sources: Callable[..., list[SceneSource]]
    tile: tuple[int, int] | None
    options: tuple[str, ...] = ()


IMPORTERS: dict[str, Importer] = {
    "dp5k": Importer(dp5k_sources, None, ("crop", "curve", "focal_length_mm", "strict")),
    "sdirt": Importer(sdirt_sources, (192, 128), ("include_unsharp",)),
    "dpdd": Importer(dpdd_sources, None, ("f_number", "curve", "strict")),
    "generic": Importer(generic_sources, None, ("strict",)),
}
"""Adapters by name; docs/data-format.md ("Importers") gives each source layout."""


def import_dataset(kind: str, src: str | os.PathLike[str], out: str | os.PathLike[str],
                   tile: tuple[int, int] | None | str = "default", seed: int = 0, resume: bool = False,
                   **options: Any) -> dict[str, list[str]]:
    """Run adapter ``kind`` on ``src`` and write the format-v1 dataset to ``out`` (``tile="default"``: the
    importer's own default; ``resume``: continue a partial import, :func:`~.writer.write_imported`). Options the
    importer does not take are ignored when None (or False), else an error. OUT is checked before SRC is read."""
    check_out_dir(Path(out), create=False)
    if not resume:
        read_previous(Path(out), resume=False)  # an existing dataset is refused before SRC is read
    if kind not in IMPORTERS:
        raise BadInputError(f"unknown import source {kind!r} (known: {', '.join(IMPORTERS)})")
    imp = IMPORTERS[kind]
    bad = sorted(k for k, v in options.items() if v not in (None, False) and k not in imp.options)
    if bad:
        raise BadInputError(f"option(s) {', '.join(bad)} do not apply to 'import {kind}'")
    opts = {k: v for k, v in options.items() if v is not None and k in imp.options}
    size = imp.tile if tile == "default" else tile
    return write_imported(out, imp.sources(src, **opts), tile=size, seed=seed, source=f"dp5k import {kind}",  # type: ignore[arg-type]
                          resume=resume)
