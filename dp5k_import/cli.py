"""The ``dp5k import`` command."""

from __future__ import annotations

import json
from pathlib import Path

import click

from dp5k_common.errors import BadInputError


@click.command("import")
@click.argument("kind", type=click.Choice(["sdirt"]))
@click.argument("src", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--tile", default="192x128", show_default=True, help="Cut each frame into WxH tiles (pairs); 'none' keeps whole frames.")
@click.option("--seed", default=0, show_default=True, help="Seed of the scene split.")
def import_command(kind: str, src: Path, out: Path, tile: str, seed: int) -> None:
    """Import public DP data (KIND: sdirt) from SRC into a format-v1 dataset at OUT."""
    from .sources import import_dataset

    if not src.exists():
        raise BadInputError("source folder not found", where=src)
    size = None
    if tile.lower() != "none":
        try:
            w, h = (int(v) for v in tile.lower().split("x"))
        except ValueError as exc:
            raise BadInputError(f"--tile must be WxH or none, got {tile!r}", where="--tile") from exc
        size = (w, h)
    splits = import_dataset(kind, src, out, tile=size, seed=seed)
    click.echo(json.dumps({k: len(v) for k, v in splits.items()}))
