"""The released DP5K dataset (Li, Guo et al., ICCP 2023: "Learning to Synthesize Photorealistic Dual-pixel Images
from RGBD frames"), processed version, 16-bit or 8-bit.

Layout (facts from the release's own reader ``our_simulator/dataset.py`` and ``data_processing/step1..3`` in
feiran-l/Neural-Dual-Pixel-Simulator)::

    ROOT/{train,val,test}/<scene>/meta_data.h5   focus_dis_0, focus_dis_1 (mm), AF_point_0, AF_point_1 ([x, y]
                                                 in the 1680 x 1120 frame), M0, M1 (camera matrices, fx in px at
                                                 1680 px width on a 36 mm sensor), d0, d1, R, t, pixel_size, ...
    ROOT/<split>/<scene>/cam{0,1}/FN_22.png      the sharp f/22 frame
                                  dep.png        16-bit depth in mm, 0 = invalid (also in the 8-bit release)
                                  FN_<N>_l.png, FN_<N>_r.png, FN_<N>_c.png   left, right, combined at f/N

The f-numbers are read from the file names (1.8, 2, 2.8, 4, 5.6 in the release; its scripts also know 1.4).
The reader crops a fixed region of interest per camera (rows 38-1062, columns 88-1112 for cam0 and 488-1512 for
cam1); ``crop`` chooses it. The thin-lens focal length is 85 mm and the pixel pitch 36 mm / frame width (the
reader's ``thin_lens_focal_len_in_mm`` and ``pixel_size``); its CoC is Eq. 6 / pitch, as dp5k's.

Images come from Canon DPP (paper, section 4), whose output is sRGB-encoded: ``curve`` = ``srgb`` undoes it (8- and
16-bit alike); ``linear`` takes the values as they are. The exposure of the views relative to ``_c`` and of the
sharp frame relative to ``_c`` is measured per capture (:mod:`dp5k_import.exposure`) and recorded in
params.json ``"exposure"``; the pairs are on the combined frame's linear scale.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from dp5k_common.errors import BadInputError

from .capture import Capture, Frames, SceneSource, read_depth_mm_u16, read_linear_rgb, same_size
from .exposure import measure_exposure

RELEASE_CROPS: dict[str, tuple[int, int, int, int]] = {"cam0": (38, 1062, 88, 1112), "cam1": (38, 1062, 488, 1512)}
"""The release reader's regions of interest, (row0, row1, col0, col1), end exclusive, in the 1680 x 1120 frame."""
FOCAL_LENGTH_MM = 85.0
SENSOR_WIDTH_MM = 36.0
SHARP_F_NUMBER = 22.0
CAMERAS = ("cam0", "cam1")
_VIEW = re.compile(r"^FN_(\d+(?:\.\d+)?)_l\.png$")
SOURCE = "DP5K release (Li, Guo et al., ICCP 2023; feiran-l/Neural-Dual-Pixel-Simulator)"


def read_meta(path: Path) -> dict[str, np.ndarray]:
    """Every dataset of ``meta_data.h5`` as a numpy array; a BadInputError naming the file when unreadable."""
    import h5py

    if not path.is_file():
        raise BadInputError("missing file", where=path)
    try:
        with h5py.File(path, "r") as f:
            return {k: np.asarray(v) for k, v in f.items() if isinstance(v, h5py.Dataset)}
    except OSError as exc:
        raise BadInputError(f"not a readable HDF5 file ({exc})", where=path) from exc


def _meta_value(meta: dict[str, np.ndarray], key: str, shape: tuple[int, ...], where: Path) -> np.ndarray:
    if key not in meta:
        raise BadInputError(f"lacks '{key}'", where=where)
    v = np.asarray(meta[key], dtype=np.float64)
    if v.size != int(np.prod(shape)) or not np.isfinite(v).all():
        raise BadInputError(f"'{key}' must be {int(np.prod(shape))} finite number(s), got {v.ravel()[:9].tolist()}", where=where)
    return v.reshape(shape)


def f_numbers_of(cam_dir: Path) -> list[float]:
    """The f-numbers of a camera folder, from its ``FN_<N>_l.png`` files, ascending."""
    if not cam_dir.is_dir():
        raise BadInputError("missing camera folder", where=cam_dir)
    found = sorted({float(m.group(1)) for p in cam_dir.iterdir() if (m := _VIEW.match(p.name))})
    if not found:
        raise BadInputError("no DP views FN_<N>_l.png", where=cam_dir)
    return found


def _fn_name(N: float) -> str:
    """The release's spelling of an f-number in file names: 2 -> '2', 1.8 -> '1.8'."""
    return f"{N:g}"


def crop_box(crop: str | tuple[int, int, int, int] | None, cam: str, size: tuple[int, int], where: Path
             ) -> tuple[int, int, int, int]:
    """(row0, row1, col0, col1) for ``crop``: ``"release"`` (the reader's ROI), ``"none"`` / None (whole frame)
    or an explicit box; it must lie inside the (W, H) frame."""
    W, H = size
    if crop is None or crop == "none":
        return 0, H, 0, W
    box = RELEASE_CROPS[cam] if crop == "release" else crop
    if isinstance(box, str):
        raise BadInputError(f"unknown crop {crop!r} (release, none or ROW0:ROW1,COL0:COL1)")
    r0, r1, c0, c1 = (int(v) for v in box)
    if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
        raise BadInputError(f"crop rows {r0}-{r1}, columns {c0}-{c1} do not fit the {W}x{H} frame (--crop none, or "
                            f"CAM=ROW0:ROW1,COL0:COL1)", where=where)
    return r0, r1, c0, c1


def _camera_captures(scene_dir: Path, split: str, cam: str, k: int, meta: dict[str, np.ndarray], cfg: dict[str, Any]
                     ) -> Iterator[Capture]:
    """The pairs of one camera of one scene (one per f-number)."""
    cam_dir = scene_dir / cam
    h5 = scene_dir / "meta_data.h5"
    focus_mm = float(_meta_value(meta, f"focus_dis_{k}", (1,), h5)[0])
    af = _meta_value(meta, f"AF_point_{k}", (2,), h5)
    M = _meta_value(meta, f"M{k}", (3, 3), h5)
    f_numbers = f_numbers_of(cam_dir)
    sharp, sharp_stored = read_linear_rgb(cam_dir / "FN_22.png", cfg["curve"])
    depth = read_depth_mm_u16(cam_dir / "dep.png")
    H, W = same_size(cam_dir, **{"FN_22.png": sharp, "dep.png": depth})
    r0, r1, c0, c1 = crop_box(cfg["crop"].get(cam, "release") if isinstance(cfg["crop"], dict) else cfg["crop"],
                              cam, (W, H), cam_dir)
    pitch = cfg["sensor_width_mm"] / W
    if focus_mm <= cfg["focal_length_mm"]:
        raise BadInputError(f"focus_dis_{k} = {focus_mm} mm is not beyond the {cfg['focal_length_mm']} mm focal length", where=h5)
    crop = (slice(r0, r1), slice(c0, c1))
    for N in f_numbers:
        n = _fn_name(N)
        fr = Frames(cfg["curve"])
        fr.note("FN_22.png", sharp_stored)
        left = fr.read(f"FN_{n}_l.png", cam_dir / f"FN_{n}_l.png")
        right = fr.read(f"FN_{n}_r.png", cam_dir / f"FN_{n}_r.png")
        comb = fr.read(f"FN_{n}_c.png", cam_dir / f"FN_{n}_c.png")
        same_size(cam_dir, **{"FN_22.png": sharp, f"FN_{n}_l.png": left, f"FN_{n}_r.png": right, f"FN_{n}_c.png": comb})
        exp = measure_exposure(left[crop], right[crop], sharp[crop], comb[crop], where=str(cam_dir / f"FN_{n}_*.png"))
        warns = fr.settle(left[crop], right[crop], sharp[crop], comb[crop], exp.combined_residual, cfg["strict"], cam_dir)
        lo, ro, so = exp.apply(left[crop], right[crop], sharp[crop])
        yield Capture(
            scene=scene_dir.name, sharp=so, left=lo, right=ro, depth_mm=depth[crop].copy(), f_number=N,
            focus_distance_mm=focus_mm, focal_length_mm=cfg["focal_length_mm"], pixel_pitch_mm=pitch, camera=cam,
            split=split, focus_point_px=(float(af[0]) - c0, float(af[1]) - r0),
            frame_origin_px=(c0, r0) if (r0, r1, c0, c1) != (0, H, 0, W) else None, frame_size=(W, H),
            extra={"source": SOURCE, "sharp_f_number": SHARP_F_NUMBER, "exposure": exp.to_json(),
                   "transfer_curve": cfg["curve"], "bit_depth": fr.bits,
                   "pinhole_focal_length_mm": float(M[0, 0]) * pitch, "release_split": split,
                   **({"input_warnings": warns} if warns else {})},
        )


def _scene_captures(scene_dir: Path, split: str, cfg: dict[str, Any]) -> Iterator[Capture]:
    meta = read_meta(scene_dir / "meta_data.h5")
    for k, cam in enumerate(CAMERAS):
        yield from _camera_captures(scene_dir, split, cam, k, meta, cfg)


def dp5k_sources(src: str | os.PathLike[str], crop: str | dict[str, Any] = "release", curve: str = "srgb",
                 focal_length_mm: float = FOCAL_LENGTH_MM, sensor_width_mm: float = SENSOR_WIDTH_MM,
                 strict: bool = False) -> list[SceneSource]:
    """Scenes of a DP5K release root (module docstring), in their own splits.

    Args:
        src: the release root holding ``train/``, ``val/``, ``test/`` (any of them).
        crop: ``"release"`` (default: the reader's ROI per camera), ``"none"``, or ``{"cam0": box, "cam1": box}``
            with boxes (row0, row1, col0, col1) or ``"release"`` / ``"none"``.
        curve: transfer curve of the images (``srgb`` or ``linear``).
        focal_length_mm: thin-lens focal length (the release reader's 85 mm).
        sensor_width_mm: sensor width; the pixel pitch is this / the frame width (36 / 1680 mm in the release).
        strict: refuse a scene with inconsistent files (a gray frame beside colour ones, 8 and 16-bit mixed, a
            curve that does not linearise) instead of warning.
    """
    root = Path(src)
    splits = [s for s in ("train", "val", "test") if (root / s).is_dir()]
    if not splits:
        raise BadInputError("no train/, val/ or test/ folder (expected ROOT/<split>/<scene>/meta_data.h5)", where=root)
    cfg = {"crop": crop, "curve": curve, "focal_length_mm": float(focal_length_mm), "sensor_width_mm": float(sensor_width_mm),
           "strict": strict}
    out = []
    for split in splits:
        for scene_dir in sorted(p for p in (root / split).iterdir() if p.is_dir() and not p.name.startswith(".")):
            out.append(SceneSource(scene_dir.name, scene_dir, lambda d=scene_dir, s=split: _scene_captures(d, s, cfg), split))
    if not out:
        raise BadInputError("no scene folders under the split folders", where=root)
    return out
