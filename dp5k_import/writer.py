"""Write imported captures as a format-v1 dataset: scene by scene, optional tiling, splits, atomic pairs.

Tiles carry ``crop_origin_px`` and ``full_image_size`` in params.json so field positions stay known
(``dp5k diagnose`` uses them; ``focus_point_px`` is moved into tile coordinates). A capture that is itself a
crop of its camera frame (the DP5K release's region of interest) carries the same keys.

A scene whose files are malformed is reported (scene and file) and none of its pairs stay; the other scenes are
written, ``dataset.json`` lists them (``import_failures``), and :class:`PartialFailureError` (exit 8) ends the
import; ``resume`` then keeps what was written and retries the rest. Every pair records its source capture
(``source_id``) and sources, not tiles, are split (:mod:`.plan`). ``report.md`` / ``report.json`` and a preview per
source (:mod:`.report`) say what was imported.
"""

from __future__ import annotations

import logging
import os
import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from dp5k_common.dataset import SPLITS, PairParams, write_index, write_pair
from dp5k_common.errors import BadInputError, PartialFailureError
from dp5k_common.optics import coc_diameter_px
from dp5k_common.outdir import check_out_dir
from dp5k_common.progress import progress

from .capture import Capture, SceneSource
from .plan import read_previous, safe_ids, split_note, split_sources
from .report import PREVIEWS, write_preview, write_report

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


def _write_capture(root: Path, cap: Capture, tile: tuple[int, int] | None, source_id: str, source_name: str | None
                   ) -> list[str]:
    """Write one capture's pair(s) (scene ids from ``source_id``); returns the pair ids written."""
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
        scene = f"{source_id}_t{y0 // h}{x0 // w}" if tiled else source_id
        pid = f"{scene}_{cap.camera}_f{cap.f_number:g}"
        extra = {**cap.extra, "source_id": source_id, **({"source_name": source_name} if source_name else {})}
        if tiled or cap.frame_origin_px is not None:
            Wf, Hf = cap.frame_size or (W, H)
            extra.update({"crop_origin_px": [ox + x0, oy + y0], "full_image_size": [int(Wf), int(Hf)]})
        params = PairParams(pid, scene, cap.camera, cap.f_number, cap.focus_distance_mm, cap.focal_length_mm,
                            cap.pixel_pitch_mm, (float(fx) - x0, float(fy) - y0), (w, h), extra)
        sl = (slice(y0, y0 + h), slice(x0, x0 + w))
        write_pair(root, params, sharp=np.clip(cap.sharp[sl], 0, 1), left=np.clip(cap.left[sl], 0, 1),
                   right=np.clip(cap.right[sl], 0, 1), depth_mm=cap.depth_mm[sl],
                   coc_px=np.nan_to_num(coc[sl], nan=0.0), overwrite=True)
        written.append(pid)
    return written


def write_imported(out: str | os.PathLike[str], sources: Iterable[SceneSource | Capture],
                   tile: tuple[int, int] | None = None, seed: int = 0, source: str = "import", resume: bool = False,
                   **index_extra: object) -> dict[str, list[str]]:
    """Write scenes (optionally tiled) as a format-v1 dataset, with report.md / report.json and a preview per
    source; returns the splits (pair ids).

    Every pair records its source (params.json ``source_id``, and ``source_name`` when the source's own name is not
    a safe id: ``my scene`` -> ``my_scene``); sources keep their own split (``SceneSource.split`` or
    ``Capture.split``), the others are split by source before anything is read (:mod:`.plan`), so a source that
    fails now lands where it would have. A bare :class:`Capture` is a source of its own.

    Args:
        resume: an existing import at ``out`` is continued: sources whose pairs are all there are kept untouched,
            the others (failed before, or new) are imported; without it an existing dataset is refused.

    Raises:
        BadInputError: OUT cannot be written, the output already holds a dataset (and not ``resume``), a tile does
            not fit, nothing could be imported (the error of the only scene, or a list of the scenes' errors).
        PartialFailureError: some scenes failed (named with their file and problem); the others were written.
    """
    root = Path(out)
    check_out_dir(root, create=False)
    prev = read_previous(root, resume)
    items = [s if isinstance(s, SceneSource) else SceneSource(s.scene, Path(s.scene), lambda c=s: iter([c]), s.split)
             for s in sources]
    ids = safe_ids([s.scene for s in items])
    own = {ids[s.scene]: s.split for s in items if s.split is not None}
    bad = sorted({sp for sp in own.values() if sp not in SPLITS})
    if bad:
        raise BadInputError(f"unknown split(s) {', '.join(bad)} (train, val, test)", where=root)
    split_of = {**split_sources([ids[s.scene] for s in items if s.split is None], seed), **own,
                **{sid: sp for sid, (sp, _) in prev.kept.items()}}
    todo = [s for s in items if ids[s.scene] not in prev.kept]
    pairs_of = {sid: pids for sid, (_, pids) in prev.kept.items()}
    records = {sid: prev.records.get(sid, {"source_id": sid, "split": sp, "pairs": len(pids)})
               for sid, (sp, pids) in prev.kept.items()}
    failed: list[tuple[SceneSource, BadInputError]] = []
    for src in progress(todo, desc="import", unit="scene"):
        sid = ids[src.scene]
        try:
            pairs_of[sid], records[sid], split_of[sid] = _import_source(root, src, sid, split_of[sid], tile)
        except BadInputError as exc:
            failed.append((src, exc))
            log.error("scene %s not imported: %s", src.scene, exc.one_line())
    if not pairs_of:
        if len(failed) == 1:
            raise failed[0][1]
        if failed:
            raise BadInputError(f"no scene could be imported ({_summary(failed)})", where=root)
        raise BadInputError("nothing to import", where=root)
    done = {sid: split_of[sid] for sid in pairs_of}
    note = split_note(done, own=bool(own))
    if note:
        log.warning("%s", note)
    splits: dict[str, list[str]] = {name: [] for name in SPLITS}
    for sid in sorted(pairs_of):
        splits[split_of[sid]] += pairs_of[sid]
    failures = [{"scene": src.scene, "source_id": ids[src.scene], "split": split_of[ids[src.scene]],
                 "error": exc.one_line()} for src, exc in failed]
    write_index(root, splits, source=source, **index_extra, import_failures=failures)
    write_report(root, source, splits, [records[sid] for sid in sorted(records)], failures, note, tile,
                 resumed=bool(prev.kept))
    if failed:
        raise PartialFailureError(f"{len(failed)} of {len(items)} scenes not imported ({_summary(failed)}); the "
                                  f"others are in the dataset (dataset.json 'import_failures'; fix them and run again "
                                  f"with --resume)", where=root)
    return splits


def _import_source(root: Path, src: SceneSource, sid: str, split: str, tile: tuple[int, int] | None
                   ) -> tuple[list[str], dict[str, Any], str]:
    """Load and write one source: its pair ids, its report record and its split (a capture's own split wins when
    the source has none). On any error none of its pairs (nor its preview) stay."""
    written: list[str] = []
    name = src.scene if sid != src.scene else None
    record: dict[str, Any] = {"source_id": sid, **({"name": src.scene} if name else {}), "captures": []}
    cap_splits: set[str] = set()
    try:
        for k, cap in enumerate(src.load()):
            if cap.split is not None:
                if cap.split not in SPLITS:
                    raise BadInputError(f"unknown split {cap.split!r}", where=src.where)
                cap_splits.add(cap.split)
            if len(cap_splits) > 1:
                raise BadInputError(f"the captures of one source are in different splits ({', '.join(sorted(cap_splits))})",
                                    where=src.where)
            written += _write_capture(root, cap, tile, sid, name)
            record["captures"].append({"camera": cap.camera, "f_number": cap.f_number,
                                       "exposure": cap.extra.get("exposure"),
                                       "input_warnings": list(cap.extra.get("input_warnings", []))})
            if k == 0:
                record["preview"] = write_preview(root, sid, cap, tile)
    except BadInputError:
        for pid in written:  # a failed scene leaves none of its pairs behind
            shutil.rmtree(root / "pairs" / pid, ignore_errors=True)
        (root / PREVIEWS / f"{sid}.png").unlink(missing_ok=True)
        raise
    split = cap_splits.pop() if cap_splits and src.split is None else split
    record.update(split=split, pairs=len(written))
    return written, record, split


def _summary(failed: list[tuple[SceneSource, BadInputError]], n: int = 3) -> str:
    text = "; ".join(f"scene {src.scene}: {exc.one_line()}" for src, exc in failed[:n])
    return text + (f"; ... {len(failed) - n} more" if len(failed) > n else "")
