"""Turn pairs of a dataset into off-the-shelf-style RGBD frames (image, depth, pinhole intrinsics) for
``dp5k synthesize``: the input a user would bring from e.g. Hypersim or NYU."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dp5k_common.dataset import DatasetReader
from dp5k_common.io import to_uint16, write_json_atomic, write_png16
from dp5k_common.optics import pinhole_focal_length_mm


def write_rgbd_frames(dataset: Path, out: Path, count: int) -> list[Path]:
    """Write ``count`` frames ``out/<frame>/{image.png (linear 16-bit), depth.png (mm), intrinsics.json}``.

    The pinhole focal length in px is the thin lens's image distance for the pair's focus (Eq. 7 inverted)
    divided by the pixel pitch, principal point at the image centre.
    """
    reader = DatasetReader(dataset)
    frames = []
    seen_scenes: set[str] = set()
    for pid in reader.ids():
        params = reader.params(pid)
        if params.scene in seen_scenes:
            continue
        seen_scenes.add(params.scene)
        pair = reader.load(pid)
        folder = out / f"frame{len(frames):03d}"
        W, H = params.image_size
        f_px = pinhole_focal_length_mm(params.focal_length_mm, params.focus_distance_mm) / params.pixel_pitch_mm
        write_png16(folder / "image.png", to_uint16(pair.sharp))
        write_png16(folder / "depth.png", np.clip(np.rint(pair.depth_mm), 0, 65535).astype(np.uint16))
        write_json_atomic(folder / "intrinsics.json", {"fx": f_px, "fy": f_px, "cx": (W - 1) / 2, "cy": (H - 1) / 2, "width": W, "height": H})
        frames.append(folder)
        if len(frames) >= count:
            break
    return frames
