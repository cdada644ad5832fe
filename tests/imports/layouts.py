"""Writers of public source layouts from a format-v1 dataset (test support for the importers' round trips).

Each writes exactly the files the source's own readers open, encoded as that source encodes them (sRGB, 8 or
16-bit), with deliberately different exposure scales for the views, the combined frame and the sharp frame, so
that an importer which assumed a scale instead of measuring it would fail the round trip.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dp5k_common.dataset import DatasetReader
from dp5k_common.transfer import linear_to_srgb

VIEW_SCALE = 1.6
"""Each release view is written at this multiple of its format-v1 value (DPP writes full-brightness views)."""
SHARP_SCALE = 0.7
"""The sharp frame is written at this multiple (its own exposure)."""


def write_image(path: Path, linear: np.ndarray, bits: int = 16) -> None:
    """sRGB-encode a linear (H, W, 3) image in [0, 1] and write it as an 8/16-bit PNG (RGB order in memory)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    top = (1 << bits) - 1
    v = np.rint(linear_to_srgb(linear) * top).astype(np.uint16 if bits == 16 else np.uint8)
    assert cv2.imwrite(str(path), cv2.cvtColor(v, cv2.COLOR_RGB2BGR))


def write_dp5k_scene(reader: DatasetReader, scene: str, dest: Path, bits: int = 16) -> None:
    """The DP5K release layout of one studio scene: ``dest/meta_data.h5`` and ``dest/cam{0,1}/...``.

    meta_data.h5 holds what the release reader reads (focus_dis_k in mm, AF_point_k as [x, y], M_k) plus the other
    calibration keys of the release (d_k, R, t, pixel_size)."""
    import h5py

    meta: dict[str, np.ndarray] = {}
    for k, cam in enumerate(("cam0", "cam1")):
        pids = [p for p in reader.ids() if reader.params(p).scene == scene and reader.params(p).camera == cam]
        first = reader.load(pids[0])
        W, H = first.params.image_size
        pitch = first.params.pixel_pitch_mm
        f_px = first.params.focal_length_mm / pitch
        meta[f"focus_dis_{k}"] = np.float64(first.params.focus_distance_mm)
        meta[f"AF_point_{k}"] = np.array(first.params.focus_point_px, np.int64)
        meta[f"M{k}"] = np.array([[f_px, 0, W / 2], [0, f_px, H / 2], [0, 0, 1]], np.float64)
        meta[f"d{k}"] = np.zeros(5)
        d = dest / cam
        write_image(d / "FN_22.png", first.sharp * SHARP_SCALE, bits)
        d.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(d / "dep.png"), first.depth_mm.astype(np.uint16))
        for pid in pids:
            p = reader.load(pid)
            n = f"{p.params.f_number:g}"
            write_image(d / f"FN_{n}_l.png", p.left * VIEW_SCALE, bits)
            write_image(d / f"FN_{n}_r.png", p.right * VIEW_SCALE, bits)
            write_image(d / f"FN_{n}_c.png", p.left + p.right, bits)
    meta.update(R=np.eye(3), t=np.array([[-300.0], [0.0], [0.0]]), pixel_size=np.float64(pitch))
    with h5py.File(dest / "meta_data.h5", "w") as f:
        for key, value in meta.items():
            f.create_dataset(key, data=value)


def write_dpdd_scene(reader: DatasetReader, pair_id: str, root: Path, split: str, bits: int = 16) -> None:
    """The DPDD layout of one pair: ``root/{split}_{c,l,r}/{source,target}/<pair_id>.png``."""
    p = reader.load(pair_id)
    write_image(root / f"{split}_c" / "source" / f"{pair_id}.png", p.left + p.right, bits)
    write_image(root / f"{split}_c" / "target" / f"{pair_id}.png", p.sharp * SHARP_SCALE, bits)
    write_image(root / f"{split}_l" / "source" / f"{pair_id}.png", p.left * VIEW_SCALE, bits)
    write_image(root / f"{split}_r" / "source" / f"{pair_id}.png", p.right * VIEW_SCALE, bits)
