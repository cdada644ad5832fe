"""Test helper: small format-v1 datasets rendered by the base model with one planted effect component.

Used before (and besides) the studio: scenes are textured slanted planes with occluding rectangles.
Planted parameters are returned to the test, never written where diagnose could read them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dp5k_common.dataset import PairParams, write_index, write_pair
from dp5k_common.optics import coc_diameter_px
from neural_dp.simulators.base.components import COMPONENTS
from dp5k_learn.batch import DPBatch
from neural_dp.simulators.base import BaseModel


def texture(rng: np.random.Generator, H: int, W: int) -> np.ndarray:
    """(H, W, 3) multi-scale random colour texture in [0.05, 0.95]."""
    img = np.zeros((H, W, 3))
    for scale, amp in ((4, 0.5), (8, 0.3), (16, 0.2)):
        small = rng.uniform(0, 1, (H // scale + 2, W // scale + 2, 3))
        big = np.kron(small, np.ones((scale, scale, 1)))[:H, :W]
        img += amp * big
    sharp_edges = (rng.uniform(0, 1, (H // 2 + 1, W // 2 + 1, 1)) > 0.7)
    img = 0.6 * img + 0.3 * np.kron(sharp_edges, np.ones((2, 2, 1)))[:H, :W]
    return np.clip(0.05 + 0.9 * img / img.max(), 0.05, 0.95)


def scene(rng: np.random.Generator, H: int, W: int, behind_focus: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Sharp image and depth (mm): a slanted background plus two nearer rectangles (at 800-1300 mm, in front of
    the 1500 mm focus; at 1650-1750 mm with ``behind_focus``, so that every pixel is behind focus)."""
    sharp = texture(rng, H, W)
    yy, xx = np.mgrid[0:H, 0:W]
    d0, d1 = rng.uniform(1800, 4000), rng.uniform(1800, 4000)
    depth = d0 + (d1 - d0) * xx / W
    for _ in range(2):
        h, w = int(rng.integers(H // 4, H // 2)), int(rng.integers(W // 5, W // 3))
        y0, x0 = int(rng.integers(0, H - h)), int(rng.integers(0, W - w))
        depth[y0 : y0 + h, x0 : x0 + w] = rng.uniform(1650, 1750) if behind_focus else rng.uniform(800, 1300)
        sharp[y0 : y0 + h, x0 : x0 + w] = texture(rng, h, w)
    return sharp.astype(np.float32), depth.astype(np.float32)


def make_planted_dataset(
    root: Path, effect: str | None, params: dict[str, float], scenes: int = 8, size: tuple[int, int] = (128, 96), seed: int = 0,
    noise_sigma: float = 0.0, behind_focus: bool = False,
) -> None:
    """Write a dataset: ``scenes`` scenes x 2 f-numbers, rendered with the base model (+ ``effect``); with
    ``behind_focus`` every pixel lies behind focus (:func:`scene`)."""
    W, H = size
    rng = np.random.default_rng(seed)
    model = BaseModel(rim_softness_px=0.8, gain=1.0)
    if effect is not None:
        comp = COMPONENTS[effect]()
        comp.params.update(params)
        model = model.with_component(comp)
    names = [f"sc{i:02d}" for i in range(scenes)]
    split_of = {n: ("test" if i % 4 == 3 else "val" if i % 4 == 2 and i < 4 else "train") for i, n in enumerate(names)}
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    for sc in names:
        sharp, depth = scene(rng, H, W, behind_focus)
        for N in (2.0, 2.8):
            pid = f"{sc}_cam0_f{N}"
            p = PairParams(pid, sc, "cam0", N, 1500.0, 50.0, 0.05 * 128 / W, (W / 2, H / 2), (W, H))
            coc = coc_diameter_px(depth, 1500.0, 50.0, N, p.pixel_pitch_mm).astype(np.float32)
            b = DPBatch(
                sharp=torch.from_numpy(sharp.transpose(2, 0, 1))[None],
                coc_px=torch.from_numpy(coc)[None, None],
                depth_mm=torch.from_numpy(depth)[None, None],
                valid=torch.ones(1, 1, H, W, dtype=torch.bool),
                f_number=torch.tensor([N]),
                focus_distance_mm=torch.tensor([1500.0]),
                focal_length_mm=torch.tensor([50.0]),
                pixel_pitch_mm=torch.tensor([p.pixel_pitch_mm]),
                focus_point_px=torch.tensor([[W / 2, H / 2]]),
            )
            l, r = model(b)
            l = l[0].numpy().transpose(1, 2, 0)
            r = r[0].numpy().transpose(1, 2, 0)
            if noise_sigma > 0:
                l = l + rng.normal(0, noise_sigma, l.shape)
                r = r + rng.normal(0, noise_sigma, r.shape)
            write_pair(root, p, sharp=sharp, left=np.clip(l, 0, 1), right=np.clip(r, 0, 1), depth_mm=depth, coc_px=coc)
            splits[split_of[sc]].append(pid)
    write_index(root, splits, source="tests/diagnose/plant.py")
