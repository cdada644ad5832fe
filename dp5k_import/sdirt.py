"""Sdirt (He et al., ICCV 2025, MIT): the Canon EOS R6 Mark II + RF50 real sample set.

Fronto-parallel targets ``flat/<set>/<distance_mm>/{f4,f20}/{l,r}.png``, 8-bit sRGB views from Canon DPP at
768 x 512 (RF50 at f/4, focus 1 m). The f/20 pair is the sharp frame.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dp5k_common.errors import BadInputError

from .capture import Capture, read_rgb8, srgb_to_linear


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
