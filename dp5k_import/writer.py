"""Write imported captures as a format-v1 dataset: scene by scene, optional tiling, splits, atomic pairs.

Tiles carry ``crop_origin_px`` and ``full_image_size`` in params.json so field positions stay known
(``dp5k diagnose`` uses them; ``focus_point_px`` is moved into tile coordinates). A capture that is itself a
crop of its camera frame (the DP5K release's region of interest) carries the same keys.

A scene whose files are malformed is reported (scene and file) and none of its pairs stay; the other scenes are
written, ``dataset.json`` lists them, and :class:`PartialFailureError` (exit 8) ends the import.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from dp5k_common.dataset import (
    SPLITS,
    PairParams,
    split_scenes,
    write_index,
    write_pair,
)
from dp5k_common.errors import BadInputError, PartialFailureError
from dp5k_common.optics import coc_diameter_px
from dp5k_common.progress import progress

from .capture import Capture, SceneSource

log = logging.getLogger(__name__)


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


def _write_capture(root: Path, cap: Capture, tile: tuple[int, int] | None) -> list[tuple[str, str]]:
    """Write one capture's pair(s); returns (scene, pair id) per pair written."""
    H, W = cap.depth_mm.shape
    for name, img in (("sharp", cap.sharp), ("left", cap.left), ("right", cap.right)):
        if img.shape != (H, W, 3):
            raise BadInputError(f"{name} is {img.shape[1]}x{img.shape[0]}, depth {W}x{H}", where=cap.scene)
    coc = coc_diameter_px(np.where(cap.depth_mm > 0, cap.depth_mm, np.nan), cap.focus_distance_mm,
                          cap.focal_length_mm, cap.f_number, cap.pixel_pitch_mm)
    fx, fy = cap.focus_point_px if cap.focus_point_px is not None else (W / 2, H / 2)
    ox, oy = cap.frame_origin_px or (0, 0)
    written = []
    for (y0, x0, h, w) in _tiles(H, W, tile):
        tiled = tile is not None
        scene = f"{cap.scene}_t{y0 // h}{x0 // w}" if tiled else cap.scene
        pid = f"{scene}_{cap.camera}_f{cap.f_number:g}"
        extra = dict(cap.extra)
        if tiled or cap.frame_origin_px is not None:
            Wf, Hf = cap.frame_size or (W, H)
            extra.update({"crop_origin_px": [ox + x0, oy + y0], "full_image_size": [int(Wf), int(Hf)]})
        params = PairParams(pid, scene, cap.camera, cap.f_number, cap.focus_distance_mm, cap.focal_length_mm,
                            cap.pixel_pitch_mm, (float(fx) - x0, float(fy) - y0), (w, h), extra)
        sl = (slice(y0, y0 + h), slice(x0, x0 + w))
        write_pair(root, params, sharp=np.clip(cap.sharp[sl], 0, 1), left=np.clip(cap.left[sl], 0, 1),
                   right=np.clip(cap.right[sl], 0, 1), depth_mm=cap.depth_mm[sl],
                   coc_px=np.nan_to_num(coc[sl], nan=0.0), overwrite=True)
        written.append((scene, pid))
    return written


def write_imported(out: str | os.PathLike[str], sources: Iterable[SceneSource | Capture],
                   tile: tuple[int, int] | None = None, seed: int = 0, source: str = "import",
                   **index_extra: object) -> dict[str, list[str]]:
    """Write scenes (optionally tiled) as a format-v1 dataset; returns the splits (pair ids).

    Captures that carry a ``split`` keep it (tiles inherit it); the others are split by scene
    (:func:`dp5k_common.dataset.split_scenes`, seeded). A bare :class:`Capture` counts as a scene of its own.

    Raises:
        BadInputError: the output already holds a dataset, a tile does not fit, nothing could be imported
            (the error of the only scene, or a list of the scenes' errors).
        PartialFailureError: some scenes failed (named with their file and problem); the others were written.
    """
    root = Path(out)
    if (root / "dataset.json").exists():
        raise BadInputError("a dataset already exists here (imports never overwrite)", where=root / "dataset.json")
    items = list(sources)
    scene_pairs: dict[str, list[str]] = {}
    scene_split: dict[str, str] = {}
    failed: list[tuple[str, BadInputError]] = []
    for item in progress(items, desc="import", unit="scene"):
        src = item if isinstance(item, SceneSource) else SceneSource(item.scene, Path(item.scene), lambda c=item: iter([c]))
        written: list[tuple[str, str]] = []
        splits_here: dict[str, str] = {}
        try:
            for cap in src.load():
                if cap.split is not None and cap.split not in SPLITS:
                    raise BadInputError(f"unknown split {cap.split!r}", where=src.where)
                for scene, pid in _write_capture(root, cap, tile):
                    written.append((scene, pid))
                    if cap.split is not None:
                        splits_here[scene] = cap.split
        except BadInputError as exc:
            for _, pid in written:  # a failed scene leaves none of its pairs behind
                shutil.rmtree(root / "pairs" / pid, ignore_errors=True)
            failed.append((src.scene, exc))
            log.error("scene %s not imported: %s", src.scene, exc.one_line())
            continue
        for scene, pid in written:
            scene_pairs.setdefault(scene, []).append(pid)
        scene_split.update(splits_here)
    if not scene_pairs:
        if len(failed) == 1:
            raise failed[0][1]
        if failed:
            raise BadInputError(f"no scene could be imported ({_summary(failed)})", where=root)
        raise BadInputError("nothing to import", where=root)
    free = [sc for sc in scene_pairs if sc not in scene_split]
    split = split_scenes(free, seed=seed) if free else {name: [] for name in SPLITS}
    for sc, name in scene_split.items():
        split[name].append(sc)
    splits = {k: [p for sc in sorted(v) for p in scene_pairs[sc]] for k, v in split.items()}
    write_index(root, splits, source=source, **index_extra,
                import_failures=[{"scene": sc, "error": exc.one_line()} for sc, exc in failed])
    if failed:
        raise PartialFailureError(f"{len(failed)} of {len(items)} scenes not imported ({_summary(failed)}); the "
                                  f"others are in the dataset (dataset.json 'import_failures')", where=root)
    return splits


def _summary(failed: list[tuple[str, BadInputError]], n: int = 3) -> str:
    text = "; ".join(f"scene {sc}: {exc.one_line()}" for sc, exc in failed[:n])
    return text + (f"; ... {len(failed) - n} more" if len(failed) > n else "")
