"""Your own DP data: folders of left / right / sharp / depth images plus a small JSON of optics (no Python needed).

Layout::

    ROOT/optics.json                      the optics of every scene (keys below)
    ROOT[/<split>]/<scene>/left.<ext>     left DP view          (PNG, TIFF or JPEG; 8 or 16-bit; RGB or gray)
                           right.<ext>    right DP view
                           sharp.<ext>    the sharp (small-aperture) frame of the same view
                           depth.<ext>    optional: z-depth, single channel, 16-bit or float TIFF, x depth_scale_mm
                                          = mm, 0 / NaN = invalid (absent: no depth, 0 everywhere)
                           combined.<ext> optional: the full-aperture frame the views add up to; when given, the
                                          views' exposure is measured against it
                           optics.json    optional: this scene's values over the ROOT ones

Several f-numbers of one scene: ``left_f<N>.<ext>``, ``right_f<N>.<ext>`` (and ``combined_f<N>.<ext>``) instead of
``left``/``right``; the f-number is read from the name. ``<split>`` folders named train, val or test keep their
split; scenes directly under ROOT are split by scene at random (``--seed``).

optics.json keys: ``f_number`` (unless in the file names), ``focus_distance_mm``, ``focal_length_mm`` (thin lens),
``pixel_pitch_mm`` or ``sensor_width_mm`` (pitch = width / image width); optional ``sharp_f_number`` (22; 0 = an
all-in-focus image), ``curve`` (``srgb`` default, or ``linear``), ``depth_scale_mm`` (1), ``focus_point_px``
([x, y], default the centre), ``camera`` (``cam0``), ``source`` (a free text kept in params.json).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from dp5k_common.errors import BadInputError
from dp5k_common.io import read_image_raw, read_json

from .capture import CURVES, Capture, Frames, SceneSource, read_linear_rgb, same_size
from .exposure import measure_exposure

EXTS = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
SPLITS = ("train", "val", "test")
_FN = re.compile(r"^left_f(\d+(?:\.\d+)?)$")
KNOWN_KEYS = {"f_number", "focus_distance_mm", "focal_length_mm", "pixel_pitch_mm", "sensor_width_mm", "sharp_f_number",
              "curve", "depth_scale_mm", "focus_point_px", "camera", "source"}


def find_image(folder: Path, stem: str, required: bool = True) -> Path | None:
    """``folder/stem.<ext>`` for the first of :data:`EXTS` (any case) that exists."""
    for p in sorted(folder.iterdir()):
        if p.stem == stem and p.suffix.lower() in EXTS:
            return p
    if required:
        raise BadInputError(f"missing {stem}.<png|tif|jpg>", where=folder)
    return None


def load_optics(path: Path, base: dict[str, Any] | None = None) -> dict[str, Any]:
    """``base`` updated by the JSON object in ``path`` (unknown keys are an error naming them)."""
    obj = read_json(path)
    if not isinstance(obj, dict):
        raise BadInputError("optics must be a JSON object", where=path)
    unknown = sorted(set(obj) - KNOWN_KEYS)
    if unknown:
        raise BadInputError(f"unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(KNOWN_KEYS))})", where=path)
    return {**(base or {}), **obj, "_where": str(path)}


def _number(optics: dict[str, Any], key: str, positive: bool = True, default: float | None = None) -> float:
    where = optics.get("_where")
    if key not in optics:
        if default is not None:
            return default
        raise BadInputError(f"optics lack '{key}'", where=where)
    v = optics[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0) or v < 0:
        raise BadInputError(f"'{key}' must be a {'positive' if positive else 'non-negative'} number, got {v!r}", where=where)
    return float(v)


def read_depth(path: Path, scale_mm: float) -> np.ndarray:
    """Depth in mm from a single-channel 16-bit or float image times ``scale_mm``; 0 / NaN / <= 0 invalid (0)."""
    d = read_image_raw(path)
    if d.ndim != 2 or not (d.dtype == np.uint16 or np.issubdtype(d.dtype, np.floating)):
        raise BadInputError(f"depth must be single-channel 16-bit or float, got {d.dtype} with shape {d.shape}", where=path)
    mm = d.astype(np.float64) * scale_mm
    return np.where(np.isfinite(mm) & (mm > 0), mm, 0.0).astype(np.float32)


def _captures(folder: Path, scene: str, split: str | None, optics: dict[str, Any], strict: bool) -> Iterator[Capture]:
    if (folder / "optics.json").is_file():
        optics = load_optics(folder / "optics.json", optics)
    curve = optics.get("curve", "srgb")
    if curve not in CURVES:
        raise BadInputError(f"'curve' must be one of {', '.join(CURVES)}, got {curve!r}", where=optics.get("_where"))
    sharp_p = find_image(folder, "sharp")
    assert sharp_p is not None
    sharp, sharp_stored = read_linear_rgb(sharp_p, curve)
    H, W = sharp.shape[:2]
    depth_p = find_image(folder, "depth", required=False)
    depth = read_depth(depth_p, _number(optics, "depth_scale_mm", default=1.0)) if depth_p else np.zeros((H, W), np.float32)
    same_size(folder, sharp=sharp, depth=depth)
    if "pixel_pitch_mm" in optics:
        pitch = _number(optics, "pixel_pitch_mm")
    else:
        pitch = _number(optics, "sensor_width_mm") / W
    focus_mm, focal_mm = _number(optics, "focus_distance_mm"), _number(optics, "focal_length_mm")
    if focus_mm <= focal_mm:
        raise BadInputError(f"focus_distance_mm ({focus_mm}) must exceed focal_length_mm ({focal_mm})", where=optics.get("_where"))
    fp = optics.get("focus_point_px")
    if fp is not None and not (isinstance(fp, list) and len(fp) == 2 and all(isinstance(v, (int, float)) for v in fp)):
        raise BadInputError(f"'focus_point_px' must be [x, y], got {fp!r}", where=optics.get("_where"))
    stems = [p.stem for p in folder.iterdir() if p.suffix.lower() in EXTS]
    if "left" in stems:
        views = [(_number(optics, "f_number"), "left", "right", "combined")]
    else:
        fns = sorted({float(m.group(1)) for s in stems if (m := _FN.match(s))})
        if not fns:
            raise BadInputError("missing left.<png|tif|jpg> (or left_f<N>.<ext> per f-number)", where=folder)
        views = [(N, f"left_f{N:g}", f"right_f{N:g}", f"combined_f{N:g}") for N in fns]
    for N, ln, rn, cn in views:
        fr = Frames(curve)
        fr.note(sharp_p.name, sharp_stored)
        left_p, right_p = find_image(folder, ln), find_image(folder, rn)
        assert left_p is not None and right_p is not None
        left, right = fr.read(left_p.name, left_p), fr.read(right_p.name, right_p)
        comb_p = find_image(folder, cn, required=False)
        comb = fr.read(comb_p.name, comb_p) if comb_p else None
        same_size(folder, sharp=sharp, **{ln: left, rn: right}, **({cn: comb} if comb is not None else {}))
        exp = measure_exposure(left, right, sharp, comb, where=str(folder))
        warns = fr.settle(left, right, sharp, comb, exp.combined_residual, strict, folder)
        lo, ro, so = exp.apply(left, right, sharp)
        yield Capture(scene=scene, sharp=so, left=lo, right=ro, depth_mm=depth, f_number=N, focus_distance_mm=focus_mm,
                      focal_length_mm=focal_mm, pixel_pitch_mm=pitch, camera=str(optics.get("camera", "cam0")),
                      split=split, focus_point_px=None if fp is None else (float(fp[0]), float(fp[1])),
                      extra={"source": str(optics.get("source", "dp5k import generic")),
                             "sharp_f_number": _number(optics, "sharp_f_number", positive=False, default=22.0),
                             "exposure": exp.to_json(), "transfer_curve": curve, "bit_depth": fr.bits,
                             "has_depth": depth_p is not None, **({"input_warnings": warns} if warns else {})})


def generic_sources(src: str | os.PathLike[str], strict: bool = False) -> list[SceneSource]:
    """Scenes of a generic layout (module docstring); ``strict``: a scene with inconsistent files (a gray frame
    beside colour ones, 8 and 16-bit mixed, a curve that does not linearise) is refused instead of warned about."""
    root = Path(src)
    if not (root / "optics.json").is_file():
        raise BadInputError("missing optics.json (the optics of the scenes; see `dp5k import --help`)", where=root)
    optics = load_optics(root / "optics.json")
    out = []
    split_dirs = [(s, root / s) for s in SPLITS if (root / s).is_dir()]
    for split, base in split_dirs or [(None, root)]:
        for folder in sorted(p for p in base.iterdir() if p.is_dir() and not p.name.startswith(".")):
            out.append(SceneSource(folder.name, folder, lambda f=folder, s=split: _captures(f, f.name, s, optics, strict),
                                   split))
    if not out:
        raise BadInputError("no scene folders", where=root)
    return out
