"""Write imported captures as a format-v1 dataset: optional tiling, scene split, atomic pairs.

Tiles carry ``crop_origin_px`` and ``full_image_size`` in params.json so field positions stay known
(``dp5k diagnose`` uses them; ``focus_point_px`` is moved into tile coordinates).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dp5k_common.dataset import PairParams, split_scenes, write_index, write_pair
from dp5k_common.errors import BadInputError
from dp5k_common.optics import coc_diameter_px
from dp5k_common.progress import progress

from .capture import Capture


def _tiles(H: int, W: int, tile: tuple[int, int] | None) -> list[tuple[int, int, int, int]]:
    """(y0, x0, h, w) of non-overlapping tiles covering the frame (the whole frame when ``tile`` is None)."""
    if tile is None:
        return [(0, 0, H, W)]
    tw, th = tile
    if tw > W or th > H or tw < 16 or th < 16:
        raise BadInputError(f"tile {tw}x{th} does not fit the {W}x{H} frames (min 16x16)")
    ny, nx = H // th, W // tw
    oy, ox = (H - ny * th) // 2, (W - nx * tw) // 2
    return [(oy + i * th, ox + j * tw, th, tw) for i in range(ny) for j in range(nx)]


def write_imported(out: str | os.PathLike[str], captures: Iterable[Capture], tile: tuple[int, int] | None = None,
                   seed: int = 0, source: str = "import") -> dict[str, list[str]]:
    """Write captures (optionally tiled) as a format-v1 dataset; returns the splits (pair ids).

    Raises:
        BadInputError: the output already holds a dataset, or a tile does not fit.
    """
    root = Path(out)
    if (root / "dataset.json").exists():
        raise BadInputError("a dataset already exists here (imports never overwrite)", where=root / "dataset.json")
    scene_pairs: dict[str, list[str]] = {}
    for cap in progress(list(captures), desc="import", unit="capture"):
        H, W = cap.depth_mm.shape
        coc = coc_diameter_px(np.where(cap.depth_mm > 0, cap.depth_mm, np.nan), cap.focus_distance_mm,
                              cap.focal_length_mm, cap.f_number, cap.pixel_pitch_mm)
        for (y0, x0, h, w) in _tiles(H, W, tile):
            tiled = tile is not None
            scene = f"{cap.scene}_t{y0 // h}{x0 // w}" if tiled else cap.scene
            pid = f"{scene}_{cap.camera}_f{cap.f_number:g}"
            extra = dict(cap.extra)
            if tiled:
                extra.update({"crop_origin_px": [x0, y0], "full_image_size": [W, H]})
            params = PairParams(pid, scene, cap.camera, cap.f_number, cap.focus_distance_mm, cap.focal_length_mm,
                                cap.pixel_pitch_mm, (W / 2 - x0, H / 2 - y0), (w, h), extra)
            sl = (slice(y0, y0 + h), slice(x0, x0 + w))
            write_pair(root, params, sharp=np.clip(cap.sharp[sl], 0, 1), left=np.clip(cap.left[sl], 0, 1),
                       right=np.clip(cap.right[sl], 0, 1), depth_mm=cap.depth_mm[sl], coc_px=np.nan_to_num(coc[sl], nan=0.0))
            scene_pairs.setdefault(scene, []).append(pid)
    if not scene_pairs:
        raise BadInputError("nothing to import", where=root)
    split = split_scenes(list(scene_pairs), seed=seed)
    splits = {k: [p for sc in v for p in scene_pairs[sc]] for k, v in split.items()}
    write_index(root, splits, source=source)
    return splits
