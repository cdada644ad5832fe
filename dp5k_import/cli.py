"""The ``dp5k import`` command."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from dp5k_common.cli_conventions import out_option, resume_option
from dp5k_common.errors import BadInputError


def parse_crop(values: tuple[str, ...]) -> str | dict[str, Any] | None:
    """``--crop`` values: ``release`` / ``none`` (both cameras) or ``cam0=ROW0:ROW1,COL0:COL1`` per camera."""
    if not values:
        return None
    if len(values) == 1 and values[0] in ("release", "none"):
        return values[0]
    out: dict[str, Any] = {}
    for v in values:
        try:
            cam, box = v.split("=", 1)
            if box in ("release", "none"):
                out[cam] = box
                continue
            rows, cols = box.split(",")
            r0, r1 = (int(x) for x in rows.split(":"))
            c0, c1 = (int(x) for x in cols.split(":"))
        except ValueError as exc:
            raise BadInputError(f"--crop must be release, none or CAM=ROW0:ROW1,COL0:COL1, got {v!r}", where="--crop") from exc
        if cam not in ("cam0", "cam1"):
            raise BadInputError(f"--crop names camera {cam!r} (cam0 or cam1)", where="--crop")
        out[cam] = (r0, r1, c0, c1)
    return out


@click.command("import")
@click.argument("kind", type=click.Choice(["dp5k", "sdirt", "dpdd", "generic"]))
@click.argument("src", type=click.Path(path_type=Path))
@out_option("The format-v1 dataset to write (refused if it holds one, unless --resume).", legacy_positional=True)
@click.option("--tile", default=None,
              help="Cut each frame into WxH tiles (pairs); 'none' keeps whole frames. Default: 192x128 for sdirt, "
                   "whole frames for the others.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of the scene split (sources without their own).")
@click.option("--crop", "crop", multiple=True,
              help="dp5k: 'release' (default: the release reader's region of interest, cam0 rows 38-1062 x columns "
                   "88-1112, cam1 38-1062 x 488-1512), 'none', or per camera CAM=ROW0:ROW1,COL0:COL1 (repeatable).")
@click.option("--curve", type=click.Choice(["srgb", "linear"]), default=None,
              help="dp5k, dpdd: transfer curve of the images, undone on load (default srgb: Canon DPP's output, 8- "
                   "and 16-bit alike; IEC 61966-2-1).")
@click.option("--focal-length-mm", type=click.FloatRange(min=0, min_open=True), default=None,
              help="dp5k: thin-lens focal length (default 85, the release reader's).")
@click.option("--f-number", type=click.FloatRange(min=0, min_open=True), default=None, help="dpdd: f-number of the DP views (default 4; not in the files).")
@click.option("--include-unsharp", is_flag=True, default=None,
              help="sdirt: also the box and casual scenes (depth, no sharp frame): sharp = left + right at f/4, for "
                   "depth-from-DP evaluation only.")
@click.option("--strict", is_flag=True, default=False,
              help="dp5k, dpdd, generic: refuse a scene whose files disagree (a gray frame beside colour ones, 8 and "
                   "16-bit files in one pair, a --curve under which left + right does not match the combined frame) "
                   "instead of importing it with a warning.")
@resume_option("--resume continues an import at OUT that ended with failed scenes (exit 8): keeps the imported "
               "scenes, retries the failed (and any new) ones. --no-resume (the default) refuses an OUT that already "
               "holds a dataset: an import never overwrites one.", default=False)
def import_command(kind: str, src: Path, out: Path, tile: str | None, seed: int, crop: tuple[str, ...],
                   curve: str | None, focal_length_mm: float | None, f_number: float | None,
                   include_unsharp: bool | None, strict: bool, resume: bool) -> None:
    """Import public or your own DP data from SRC into a format-v1 dataset at --out OUT.

    \b
    KIND (layouts in docs/data-format.md, "Importers"):
      dp5k     the released DP5K dataset: SRC/{train,val,test}/<scene>/{meta_data.h5,cam0,cam1}; splits kept;
               exposure of the views and the sharp frame measured against FN_<N>_c; sharp_f_number 22.
      sdirt    Sdirt DP119 (or its real_sample_set): the planar targets (f/20 sharp, f/4 views, depth).
      dpdd     DPDD: SRC/{train,val,test}_{c,l,r}/{source,target}; splits kept. NO DEPTH: depth is 0 (invalid)
               everywhere and the focus distance and focal length are placeholders, so these pairs serve what
               needs no depth: real test pairs for a DP deblurring network (dp5k deblur evaluate) and the
               check of left + right against the combined frame (measured at import: params.json "exposure").
               They are not a training set for RGBD -> DP; dp5k evaluate leaves them out (it renders from depth).
      generic  your own data: SRC/optics.json and SRC[/<split>]/<scene>/{left,right,sharp[,depth,combined]}.<ext>.

    Tiles, cameras and f-numbers of one source capture (params.json source_id) always share a split; two sources
    give train and test (val empty), one gives train only. Scene folders with spaces or accents get safe ids
    (params.json source_name keeps the name). A malformed scene is reported with its file and skipped; the others
    are imported and the command then exits with code 8 (fix the scene, then --resume). An existing dataset at OUT
    is never overwritten. OUT gets report.md, report.json and previews/<source>.png. An OUT that is a file, lies
    under a file or cannot be written is refused before anything is read (exit 3).
    """
    from .sources import import_dataset

    if not src.exists():
        raise BadInputError("source folder not found", where=src)
    size: tuple[int, int] | None | str = "default"
    if tile is not None and tile.lower() == "none":
        size = None
    elif tile is not None:
        try:
            w, h = (int(v) for v in tile.lower().split("x"))
        except ValueError as exc:
            raise BadInputError(f"--tile must be WxH or none, got {tile!r}", where="--tile") from exc
        if w < 16 or h < 16:
            raise BadInputError(f"--tile must be at least 16x16, got {tile!r}", where="--tile")
        size = (w, h)
    splits = import_dataset(kind, src, out, tile=size, seed=seed, resume=resume, crop=parse_crop(crop), curve=curve,
                            focal_length_mm=focal_length_mm, f_number=f_number, include_unsharp=include_unsharp or None,
                            strict=strict)
    click.echo(json.dumps({k: len(v) for k, v in splits.items()}))
    click.echo(f"report: {out / 'report.md'}", err=True)
