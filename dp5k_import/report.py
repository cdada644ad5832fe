"""What an import says it did: ``OUT/report.json``, ``OUT/report.md`` and ``OUT/previews/<source_id>.png``.

The report gives the counts (sources, pairs per split), how the split was made, the measured exposure of every
capture (``views_gain``, ``sharp_gain``, ``headroom``, ``combined_residual``: docs/data-format.md), the warnings
about its files, the failures, and a contact sheet per source (sharp | left | right | depth | CoC of its first
capture, tile borders drawn) to look at before training on it.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dp5k_common.io import write_bytes_atomic, write_json_atomic
from dp5k_common.software import provenance
from dp5k_common.optics import coc_diameter_px
from dp5k_common.preview import contact_sheet

from .capture import Capture

PREVIEWS = "previews"
PREVIEW_WIDTH_PX = 320
"""Each image of a preview is at most this wide (the sheet is five of them)."""


def write_preview(root: Path, source_id: str, cap: Capture, tile: tuple[int, int] | None) -> str:
    """``root/previews/<source_id>.png``: the capture's contact sheet, downsized, tile borders in gray; returns its
    path relative to ``root``."""
    H, W = cap.depth_mm.shape
    s = min(1.0, PREVIEW_WIDTH_PX / W)
    size = (max(1, round(W * s)), max(1, round(H * s)))

    def small(a: np.ndarray) -> np.ndarray:
        return cv2.resize(np.asarray(a, np.float32), size, interpolation=cv2.INTER_AREA) if s < 1 else np.asarray(a, np.float32)

    coc = coc_diameter_px(np.where(cap.depth_mm > 0, cap.depth_mm, np.nan), cap.focus_distance_mm, cap.focal_length_mm,
                          cap.f_number, cap.pixel_pitch_mm)
    depth = small(cap.depth_mm)
    depth[small((cap.depth_mm > 0).astype(np.float32)) < 0.5] = 0
    images = [small(cap.sharp), small(cap.left), small(cap.right), depth,
              cv2.resize(coc.astype(np.float32), size, interpolation=cv2.INTER_NEAREST) if s < 1 else coc.astype(np.float32)]
    if tile is not None:  # tile borders, so a pair id's _t<row><col> can be found on the sheet
        tw, th = tile
        ny, nx = H // th, W // tw
        oy, ox = (H - ny * th) // 2, (W - nx * tw) // 2
        for img in images[:3]:
            for x in range(nx + 1):
                img[:, min(size[0] - 1, round((ox + x * tw) * s))] = 0.5
            for y in range(ny + 1):
                img[min(size[1] - 1, round((oy + y * th) * s)), :] = 0.5
    label = f"{source_id} {cap.camera} f/{cap.f_number:g}"
    rel = f"{PREVIEWS}/{source_id}.png"
    contact_sheet([(label, *images)], root / rel)
    return rel


def _fmt(v: Any, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec) if isinstance(v, (int, float)) else str(v)


def write_report(root: Path, command: str, splits: Mapping[str, Sequence[str]], records: list[dict[str, Any]],
                 failures: list[dict[str, Any]], split_note: str | None, tile: tuple[int, int] | None,
                 resumed: bool) -> None:
    """Write ``report.json`` and ``report.md`` at ``root`` (module docstring).

    Args:
        command: what imported (``dp5k import sdirt``).
        splits: the dataset's splits (pair ids).
        records: one per imported source: ``source_id``, ``name`` (the source's own name, when not a safe id),
            ``split``, ``pairs``, ``captures`` (camera, f-number, ``exposure``, ``input_warnings``), ``preview``.
        failures: dataset.json's ``import_failures``.
        split_note: why val or test is empty (one or two sources), or None.
        resumed: this run continued an earlier one (``--resume``).
    """
    per_split = {name: sum(1 for r in records if r.get("split") == name) for name in splits}
    summary = {"command": command, "written": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
               "resumed": resumed, "sources": len(records) + len(failures), "imported": len(records),
               "failed": len(failures), "pairs": {k: len(v) for k, v in splits.items()}, "sources_per_split": per_split,
               "tile": list(tile) if tile else None, "split_note": split_note, "scenes": records, "failures": failures,
               "provenance": provenance()}
    write_json_atomic(root / "report.json", summary)
    lines = [f"# Import report ({command})", "",
             f"{len(records)} of {len(records) + len(failures)} sources imported"
             + (" (resumed: the sources kept from the earlier run were not read again)" if resumed else "")
             + f"; {sum(len(v) for v in splits.values())} pairs"
             + (f", tiles of {tile[0]} x {tile[1]} px" if tile else "") + ".", "",
             "| split | sources | pairs |", "|---|---|---|"]
    lines += [f"| {k} | {per_split[k]} | {len(v)} |" for k, v in splits.items()]
    lines += ["", "Every pair of one source (tiles, cameras, f-numbers) is in one split (params.json `source_id`)."
              + (f" **{split_note}.**" if split_note else "")]
    if failures:
        lines += ["", "## Not imported", "", "Fix these and run the same command with `--resume`:", ""]
        lines += [f"* `{f['scene']}`: {f['error']}" for f in failures]
    warned = [(r, c) for r in records for c in r.get("captures", []) if c.get("input_warnings")]
    if warned:
        lines += ["", "## Warnings about the input files", ""]
        lines += [f"* `{r['source_id']}` {c['camera']} f/{c['f_number']:g}: {w}" for r, c in warned for w in c["input_warnings"]]
    lines += ["", "## Sources", "", "Exposure (docs/data-format.md): the gains that put the views and the sharp frame on "
              "one linear scale, and how well left + right reproduces the combined frame.", "",
              "| source | split | pairs | camera | f | views_gain | sharp_gain | headroom | combined_residual |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        name = f"`{r['source_id']}`" + (f" ({r['name']})" if r.get("name") else "")
        caps = r.get("captures") or [{}]
        for i, c in enumerate(caps):
            e = c.get("exposure") or {}
            head = f"| {name} | {r.get('split', '-')} | {r.get('pairs', '-')} " if i == 0 else "| | | "
            lines.append(head + f"| {c.get('camera', '-')} | {_fmt(c.get('f_number'), 'g')} | {_fmt(e.get('views_gain'))} | "
                         f"{_fmt(e.get('sharp_gain'))} | {_fmt(e.get('headroom'))} | {_fmt(e.get('combined_residual'), '.4f')} |")
    previews = [r for r in records if r.get("preview")]
    if previews:
        lines += ["", "## Previews", "", "sharp | left | right | depth (near blue) | CoC of each source's first capture.", ""]
        lines += [f"![{r['source_id']}]({r['preview']})" for r in previews]
    write_bytes_atomic(root / "report.md", ("\n".join(lines) + "\n").encode())
