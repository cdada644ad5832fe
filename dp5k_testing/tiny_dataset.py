"""Make tiny, valid format-v1 datasets for tests that need one without the studio."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dp5k_common.dataset import PairParams, write_index, write_pair
from dp5k_common.optics import coc_diameter_px


def make_params(pair_id: str, scene: str = "s0", W: int = 24, H: int = 16, **extra: object) -> PairParams:
    return PairParams(
        pair_id=pair_id,
        scene=scene,
        camera="cam0",
        f_number=1.8,
        focus_distance_mm=2000.0,
        focal_length_mm=85.0,
        pixel_pitch_mm=36.0 / W,
        focus_point_px=(W / 2, H / 2),
        image_size=(W, H),
        extra=dict(extra),
    )


def make_arrays(params: PairParams, seed: int = 0) -> dict[str, np.ndarray]:
    W, H = params.image_size
    rng = np.random.default_rng(seed)
    sharp = rng.uniform(0.05, 0.95, (H, W, 3))
    depth = np.tile(np.linspace(800.0, 5000.0, W), (H, 1))
    depth[0, 0] = 0.0  # one invalid pixel
    coc = coc_diameter_px(depth, params.focus_distance_mm, params.focal_length_mm, params.f_number, params.pixel_pitch_mm)
    return {
        "sharp": sharp,
        "left": sharp * 0.5,
        "right": sharp * 0.5,
        "depth_mm": depth,
        "coc_px": np.nan_to_num(coc, nan=0.0),
    }


def make_tiny_dataset(root: Path, scenes: int = 3, W: int = 24, H: int = 16) -> dict[str, list[str]]:
    """Write a dataset with one pair per scene, scene i in split train/val/test cyclically."""
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    names = ["train", "val", "test"]
    for i in range(scenes):
        params = make_params(f"s{i}_cam0_f1.8", scene=f"s{i}", W=W, H=H)
        write_pair(root, params, **make_arrays(params, seed=i))
        splits[names[i % 3]].append(params.pair_id)
    write_index(root, splits, source="tests")
    return splits
