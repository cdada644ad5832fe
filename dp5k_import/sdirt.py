"""Sdirt DP119 (He et al., ICCV 2025, MIT): real Canon EOS R6 Mark II + RF50 DP views with depth.

Layout (the repository's ``dfdp/dataset.py`` readers and ``configs/*.yml``; the shipped ``real_sample_set`` is a
subset with the same folders)::

    ROOT/flat/<set>/<distance_mm>/{f4,f20}/{l,r}.png   fronto-parallel target; f20 = the sharp frame
    ROOT/box[/rgbd]/<scene>/{l,r,d}.png                 boxes; d.png 8-bit, depth_m = gray / 255 x 10
    ROOT/casual/{iphone,orbbec}/<scene>/{l,r,d}.png     iphone: 8-bit as box; orbbec: 16-bit mm

The views are 8-bit sRGB from Canon DPP at 768 x 512, f/4, focus 1 m (repository README). Depth >= 10 m or <= 0
is invalid (their readers). ``flat`` has a sharp frame (f/20) and so forms RGBD -> DP pairs; ``box`` and
``casual`` have depth but no sharp frame: imported only on request, with ``sharp`` = left + right and
``sharp_f_number`` = 4 (the views' own blur: good for depth-from-DP evaluation, not for RGBD -> DP training).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from dp5k_common.errors import BadInputError
from dp5k_common.io import read_image_raw

from dp5k_common.transfer import srgb_to_linear

from .capture import Capture, SceneSource, read_rgb8, same_size

SDIRT_FOCUS_MM = 1000.0
SDIRT_F_NUMBER = 4.0
SDIRT_FOCAL_MM = 49.57  # lenses/rf50mm/lens_web.json "foclen"
SDIRT_SENSOR_W_MM = 36.0
SDIRT_MAX_DEPTH_MM = 10000.0
SOURCE = "Sdirt DP119 (He et al. ICCV 2025, MIT), Canon EOS R6 II + RF50, DPP sRGB linearised"


def find_sdirt_flat(src: Path) -> Path:
    """The ``flat`` folder inside an Sdirt checkout or data copy."""
    for cand in (src / "real_sample_set" / "flat", src / "flat", src):
        if cand.is_dir() and any(p.is_dir() and any(q.name.isdigit() for q in p.iterdir()) for p in cand.iterdir() if p.is_dir()):
            if cand.name == "flat" or (cand / "001").is_dir():
                return cand
    raise BadInputError("no Sdirt 'flat' folder (expected real_sample_set/flat/<set>/<distance_mm>/{f4,f20}/{l,r}.png)", where=src)


def _flat_capture(dist_dir: Path, scene: str, aperture: str, sharp: str) -> Iterator[Capture]:
    """One planar-target capture: sharp = f/20 pair, views = f/4 pair, constant depth.

    Units: the 8-bit sRGB views are linearised; each DPP view is a full-brightness image, so the views are halved
    (``left + right`` = one full-aperture image) and the sharp frame is the f/20 views' mean scaled to the f/4
    exposure (ratio of means). Depth is the folder's distance in mm; pixel pitch 36 mm / width; focus 1 m; f =
    49.57 mm (RF50 prescription).
    """
    d_mm = float(int(dist_dir.name))
    l4 = srgb_to_linear(read_rgb8(dist_dir / aperture / "l.png"))
    r4 = srgb_to_linear(read_rgb8(dist_dir / aperture / "r.png"))
    l20 = srgb_to_linear(read_rgb8(dist_dir / sharp / "l.png"))
    r20 = srgb_to_linear(read_rgb8(dist_dir / sharp / "r.png"))
    H, W = same_size(dist_dir, f4_l=l4, f4_r=r4, f20_l=l20, f20_r=r20)
    left, right = l4 / 2, r4 / 2
    sh = (l20 + r20) / 2
    gain = float((left + right).mean() / max(sh.mean(), 1e-6))
    exposure = {"views_gain": 0.5, "sharp_gain": gain, "headroom": 1.0, "combined_residual": None, "pixels": H * W,
                "sharp_from": "mean of the f/20 views"}
    yield Capture(
        scene=scene, sharp=(sh * gain).astype(np.float32), left=left, right=right,
        depth_mm=np.full((H, W), d_mm, np.float32), f_number=float(aperture.lstrip("f")),
        focus_distance_mm=SDIRT_FOCUS_MM, focal_length_mm=SDIRT_FOCAL_MM, pixel_pitch_mm=SDIRT_SENSOR_W_MM / W,
        camera="r6m2", extra={"source": SOURCE, "sharp_f_number": float(sharp.lstrip("f")), "exposure": exposure},
    )


def read_sdirt_depth_mm(path: Path, size: tuple[int, int]) -> np.ndarray:
    """Sdirt depth as mm at the views' (W, H): 16-bit = mm, 8-bit (gray or RGBA) = gray / 255 x 10 m; <= 0 or
    >= 10 m invalid (0). A larger map (box: full sensor resolution) is area-averaged over its valid pixels."""
    d = read_image_raw(path)
    if d.ndim == 3:
        d = d[..., 0]
    if d.dtype == np.uint16:
        mm = d.astype(np.float32)
    elif d.dtype == np.uint8:
        mm = d.astype(np.float32) / 255.0 * SDIRT_MAX_DEPTH_MM
    else:
        raise BadInputError(f"expected 8-bit (gray/255 x 10 m) or 16-bit (mm) depth, got {d.dtype}", where=path)
    valid = (mm > 0) & (mm < SDIRT_MAX_DEPTH_MM)
    if (mm.shape[1], mm.shape[0]) != tuple(size):
        if abs(mm.shape[1] / mm.shape[0] - size[0] / size[1]) > 0.01:
            raise BadInputError(f"depth is {mm.shape[1]}x{mm.shape[0]}, not the views' aspect ({size[0]}x{size[1]})", where=path)
        num = cv2.resize(np.where(valid, mm, 0).astype(np.float32), tuple(size), interpolation=cv2.INTER_AREA)
        den = cv2.resize(valid.astype(np.float32), tuple(size), interpolation=cv2.INTER_AREA)
        with np.errstate(invalid="ignore", divide="ignore"):
            mm = np.where(den >= 0.5, num / den, 0.0).astype(np.float32)
        valid = mm > 0
    return np.where(valid, mm, 0.0).astype(np.float32)


def _unsharp_capture(folder: Path, scene: str) -> Iterator[Capture]:
    """A box / casual scene: L/R at f/4 with depth, no sharp frame (sharp = left + right, sharp_f_number 4)."""
    left = srgb_to_linear(read_rgb8(folder / "l.png")) / 2
    right = srgb_to_linear(read_rgb8(folder / "r.png")) / 2
    H, W = same_size(folder, l=left, r=right)
    depth = read_sdirt_depth_mm(folder / "d.png", (W, H))
    yield Capture(scene=scene, sharp=(left + right).astype(np.float32), left=left, right=right, depth_mm=depth,
                  f_number=SDIRT_F_NUMBER, focus_distance_mm=SDIRT_FOCUS_MM, focal_length_mm=SDIRT_FOCAL_MM,
                  pixel_pitch_mm=SDIRT_SENSOR_W_MM / W, camera="r6m2",
                  extra={"source": SOURCE, "sharp_f_number": SDIRT_F_NUMBER, "sharp_is_views_sum": True})


def _unsharp_scenes(root: Path) -> list[tuple[str, Path]]:
    """(scene id, folder) of the box (``box/rgbd/<scene>`` or ``box/<scene>``) and casual
    (``casual/<device>/<scene>``) scenes under an Sdirt root: folders holding l.png."""
    def scenes_in(base: Path) -> list[Path]:
        return sorted(p for p in base.iterdir() if p.is_dir() and (p / "l.png").is_file()) if base.is_dir() else []

    box = root / "box" / "rgbd" if (root / "box" / "rgbd").is_dir() else root / "box"
    out = [(f"box_{p.name}", p) for p in scenes_in(box)]
    casual = root / "casual"
    for device in sorted(p for p in casual.iterdir() if p.is_dir()) if casual.is_dir() else []:
        out += [(f"casual_{device.name}_{p.name}", p) for p in scenes_in(device)]
    return out


def sdirt_sources(src: str | os.PathLike[str], aperture: str = "f4", sharp: str = "f20",
                  include_unsharp: bool = False) -> list[SceneSource]:
    """Scenes of an Sdirt DP119 copy (or its ``real_sample_set``): the planar targets, and with
    ``include_unsharp`` the box and casual scenes (module docstring)."""
    flat = find_sdirt_flat(Path(src))
    out = []
    for set_dir in sorted(p for p in flat.iterdir() if p.is_dir()):
        for dist_dir in sorted(p for p in set_dir.iterdir() if p.is_dir() and p.name.isdigit()):
            scene = f"flat{set_dir.name}_d{dist_dir.name}"
            out.append(SceneSource(scene, dist_dir, lambda d=dist_dir, s=scene: _flat_capture(d, s, aperture, sharp)))
    if include_unsharp:
        for scene, folder in _unsharp_scenes(flat.parent):
            out.append(SceneSource(scene, folder, lambda f=folder, s=scene: _unsharp_capture(f, s)))
    if not out:
        raise BadInputError("no <distance_mm>/{f4,f20} folders found", where=flat)
    return out


def sdirt_captures(src: str | os.PathLike[str], aperture: str = "f4", sharp: str = "f20") -> list[Capture]:
    """All planar-target captures at once (the first malformed one raises)."""
    return [cap for s in sdirt_sources(src, aperture, sharp) for cap in s.load()]
