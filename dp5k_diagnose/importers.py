"""Import public dual-pixel data into dataset format v1 (``dp5k import``).

The reusable core is :func:`write_imported`: it takes full-frame *captures* (sharp, left, right as linear
float images, a depth map and the imaging parameters), optionally tiles each into pairs (useful when a
dataset has few, large frames), splits by scene and writes the dataset atomically pair by pair. Tiles
carry ``crop_origin_px`` and ``full_image_size`` in params.json so field positions stay known
(``dp5k diagnose`` uses them; ``focus_point_px`` is moved into tile coordinates).

Adapters turn one public layout into captures; :func:`sdirt_captures` reads the Sdirt Canon EOS R6 II set
(He et al., ICCV 2025, MIT): fronto-parallel targets ``flat/<set>/<distance_mm>/{f4,f20}/{l,r}.png``,
8-bit sRGB views from Canon DPP at 768 x 512 (RF50 at f/4, focus 1 m). The f/20 pair is the sharp frame.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.dataset import PairParams, split_scenes, write_index, write_pair
from dp5k_common.errors import BadInputError
from dp5k_common.optics import coc_diameter_px
from dp5k_common.progress import progress

F32 = NDArray[np.float32]


@dataclass
class Capture:
    """One full-frame DP capture in dataset units.

    Attributes:
        scene: scene id (splits never share one; tiles get ``<scene>_t<row><col>``).
        sharp, left, right: (H, W, 3) float32 linear; ``left + right`` ~ full-aperture blur of ``sharp``.
        depth_mm: (H, W) float32 z-depth, 0 = invalid.
        f_number, focus_distance_mm, focal_length_mm, pixel_pitch_mm: imaging parameters.
        camera: camera id.
        extra: extra params.json keys (source, licence, ...).
    """

    scene: str
    sharp: F32
    left: F32
    right: F32
    depth_mm: F32
    f_number: float
    focus_distance_mm: float
    focal_length_mm: float
    pixel_pitch_mm: float
    camera: str = "cam0"
    extra: dict[str, Any] = field(default_factory=dict)


def srgb_to_linear(img_u8: NDArray[np.uint8]) -> F32:
    """IEC 61966-2-1 inverse transfer: 8-bit sRGB -> linear [0, 1]."""
    c = img_u8.astype(np.float32) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def read_rgb8(path: Path) -> NDArray[np.uint8]:
    """An 8-bit RGB image (RGB order); a clear error for a missing or unreadable file."""
    if not path.is_file():
        raise BadInputError("missing file", where=path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise BadInputError("not a readable image", where=path)
    if img.dtype != np.uint8:
        raise BadInputError(f"expected 8-bit, got {img.dtype}", where=path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


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


# -- Sdirt (Canon EOS R6 Mark II, RF50) ------------------------------------------------------------------

SDIRT_FOCUS_MM = 1000.0
SDIRT_FOCAL_MM = 49.57  # lenses/rf50mm/lens_web.json "foclen"
SDIRT_SENSOR_W_MM = 36.0


def find_sdirt_flat(src: Path) -> Path:
    """The ``flat`` folder inside an Sdirt checkout or data copy."""
    for cand in (src / "real_sample_set" / "flat", src / "flat", src):
        if cand.is_dir() and any(p.is_dir() and any(q.name.isdigit() for q in p.iterdir()) for p in cand.iterdir() if p.is_dir()):
            if cand.name == "flat" or (cand / "001").is_dir():
                return cand
    raise BadInputError("no Sdirt 'flat' folder (expected real_sample_set/flat/<set>/<distance_mm>/{f4,f20}/{l,r}.png)", where=src)


def sdirt_captures(src: str | os.PathLike[str], aperture: str = "f4", sharp: str = "f20") -> list[Capture]:
    """Captures of the Sdirt planar targets: sharp = f/20 pair, views = f/4 pair, constant depth.

    Units: the 8-bit sRGB views are linearised; each DPP view is a full-brightness image, so the
    views are halved (``left + right`` = one full-aperture image) and the sharp frame is the f/20 views'
    mean scaled to the f/4 exposure (ratio of means). Depth is the folder's distance in mm; pixel pitch
    36 mm / width; focus 1 m; f = 49.57 mm (RF50 prescription).
    """
    flat = find_sdirt_flat(Path(src))
    caps = []
    for set_dir in sorted(p for p in flat.iterdir() if p.is_dir()):
        for dist_dir in sorted(p for p in set_dir.iterdir() if p.is_dir() and p.name.isdigit()):
            d_mm = float(int(dist_dir.name))
            l4 = srgb_to_linear(read_rgb8(dist_dir / aperture / "l.png"))
            r4 = srgb_to_linear(read_rgb8(dist_dir / aperture / "r.png"))
            l20 = srgb_to_linear(read_rgb8(dist_dir / sharp / "l.png"))
            r20 = srgb_to_linear(read_rgb8(dist_dir / sharp / "r.png"))
            if not (l4.shape == r4.shape == l20.shape == r20.shape):
                raise BadInputError(f"views differ in size: {l4.shape}, {r4.shape}, {l20.shape}, {r20.shape}", where=dist_dir)
            H, W = l4.shape[:2]
            left, right = l4 / 2, r4 / 2
            sh = (l20 + r20) / 2
            sh = sh * float((left + right).mean() / max(sh.mean(), 1e-6))
            N = float(aperture.lstrip("f"))
            caps.append(Capture(
                scene=f"flat{set_dir.name}_d{dist_dir.name}", sharp=sh.astype(np.float32), left=left, right=right,
                depth_mm=np.full((H, W), d_mm, np.float32), f_number=N, focus_distance_mm=SDIRT_FOCUS_MM,
                focal_length_mm=SDIRT_FOCAL_MM, pixel_pitch_mm=SDIRT_SENSOR_W_MM / W, camera="r6m2",
                extra={"source": "Sdirt real_sample_set (He et al. ICCV 2025, MIT), Canon EOS R6 II + RF50, DPP sRGB linearised",
                       "sharp_f_number": float(sharp.lstrip("f"))},
            ))
    if not caps:
        raise BadInputError("no <distance_mm>/{f4,f20} folders found", where=flat)
    return caps


IMPORTERS = {"sdirt": sdirt_captures}
"""Adapters by name: ``name -> (src) -> list[Capture]``."""


def import_dataset(kind: str, src: str | os.PathLike[str], out: str | os.PathLike[str], tile: tuple[int, int] | None = None, seed: int = 0) -> dict[str, list[str]]:
    """Run adapter ``kind`` on ``src`` and write the format-v1 dataset to ``out``."""
    if kind not in IMPORTERS:
        raise BadInputError(f"unknown import source {kind!r} (known: {', '.join(IMPORTERS)})")
    return write_imported(out, IMPORTERS[kind](src), tile=tile, seed=seed, source=f"dp5k import {kind}")
