"""Training items for a physical-prior network: pairs with the physical model's views, and augmentations that
respect the DP geometry.

The physical views of a pair are rendered once, on the whole pair (as the simulator renders it at inference), and
cut, flipped and scaled with the item. Augmentations (:class:`~neural_dp.config.AugmentConfig`):

* **random crops** (redrawn until enough depth is valid, as :class:`dp5k_learn.data.DPPairDataset` does);
* **vertical flips** (``data.vflip``; the released code's): the DP split is horizontal, so nothing else changes;
* **horizontal mirror with the views swapped**: a scene mirrored left-right, seen by a left-right symmetric
  camera, gives the mirror of the right view as its left view (Eq. 2: the right PSF is the mirror of the left one)
  and the CoC keeps its sign. Sharp, depth, CoC and both physical views are mirrored, L and R swapped, the field x
  negated, and the item marked ``mirrored`` so that per-view gains stay with their photodiodes.
  ``tests/neural_dp/test_physics_first.py`` checks the physical model's own symmetry: rendering the mirrored
  inputs equals mirroring and swapping the render;
* **exposure**: sharp, views and physical views times one factor (blur is linear in light).

Every draw depends only on ``(seed, epoch, index)``, so a resumed run sees the data an uninterrupted one saw.
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from dp5k_common.dataset import DatasetReader, Pair
from dp5k_learn.batch import DPBatch, frame_field
from dp5k_learn.data import CropSpec, draw_crop

from .config import AugmentConfig
from .simulators.base import BaseModel

CACHE_BYTES = 1 << 30
"""Physical views kept in memory per dataset (an LRU by size; rendered again when dropped)."""

WHOLE_PAIR_AREA = 4
"""A train pair up to this many crop areas is rendered whole once and cached; a larger one is rendered per crop, with
a margin of half its largest |CoC| plus 16 px (what its blur can reach)."""


def _chw(a: np.ndarray) -> Tensor:
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1) if a.ndim == 3 else a[None]))


def batch_of(pair: Pair, box: tuple[int, int, int, int] | None = None) -> DPBatch:
    """A one-item batch of ``pair`` (or of its ``box`` (y0, x0, h, w)), as :func:`dp5k_learn.data.collate_dp` builds it."""
    H, W = pair.valid.shape
    y0, x0, h, w = box or (0, 0, H, W)
    sl = (slice(y0, y0 + h), slice(x0, x0 + w))
    valid = pair.valid[sl]
    p = pair.params
    (ox, oy), full = p.frame_geometry

    def one(v: float) -> Tensor:
        return torch.tensor([v], dtype=torch.float32)

    return DPBatch(
        sharp=_chw(pair.sharp[sl])[None], coc_px=_chw(np.where(valid, pair.coc_px[sl], 0).astype(np.float32))[None],
        depth_mm=_chw(np.where(valid, pair.depth_mm[sl], 0).astype(np.float32))[None], valid=_chw(valid)[None],
        f_number=one(p.f_number), focus_distance_mm=one(p.focus_distance_mm), focal_length_mm=one(p.focal_length_mm),
        pixel_pitch_mm=one(p.pixel_pitch_mm),
        focus_point_px=torch.tensor([[p.focus_point_px[0] - x0, p.focus_point_px[1] - y0]], dtype=torch.float32),
        left=_chw(pair.left[sl])[None], right=_chw(pair.right[sl])[None], pair_ids=(p.pair_id,),
        sharp_f_number=one(p.sharp_f_number), field=torch.from_numpy(frame_field((ox + x0, oy + y0), full, (w, h)))[None],
    )


@torch.no_grad()
def render_prior(prior: BaseModel, pair: Pair, box: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The physical model's (left, right) views, (h, w, 3) float32, of ``pair`` or its ``box`` (y0, x0, h, w)."""
    left, right = prior(batch_of(pair, box))
    return (left[0].float().numpy().transpose(1, 2, 0).copy(), right[0].float().numpy().transpose(1, 2, 0).copy())


class PhysicalPairs(Dataset):
    """Items of the pairs ``ids`` of ``root`` with the physical model's views (module docstring).

    Args:
        root: a format-v1 dataset (None with ``pairs``).
        ids: the pairs (of any split) to serve.
        prior: the physical model (the run's, fitted).
        crop: random crops (train items); None = whole pairs, no augmentation (validation items).
        augment: the augmentations of train items (None = none).
        seed: base seed of every draw.
        length: items per epoch (0 = one per pair).
        pairs: the pairs themselves, in memory (e.g. calibrated renders, :mod:`neural_dp.pretrain`), instead of
            reading them from ``root``.

    Items: the keys of :class:`dp5k_learn.data.DPPairDataset` plus ``prior_left``, ``prior_right`` (3, h, w) and
    ``mirrored`` (bool), which :func:`dp5k_learn.data.collate_dp` puts into the batch.
    """

    def __init__(self, root: str | os.PathLike[str] | None, ids: list[str], prior: BaseModel, *, crop: CropSpec | None = None,
                 augment: AugmentConfig | None = None, seed: int = 0, length: int = 0,
                 pairs: dict[str, Pair] | None = None) -> None:
        self.reader = DatasetReader(root) if root is not None else None
        self.ids = list(ids)
        self.prior = prior
        self.crop = crop
        self.augment = augment if crop is not None else None
        self.seed = seed
        self.length = length or len(self.ids)
        self.epoch = 0
        self._pairs: dict[str, Pair] = dict(pairs or {})
        self._views: OrderedDict[str, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._bytes = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.length

    def pair(self, pair_id: str) -> Pair:
        if pair_id not in self._pairs:
            assert self.reader is not None
            self._pairs[pair_id] = self.reader.load(pair_id)
        return self._pairs[pair_id]

    def views(self, pair_id: str) -> tuple[np.ndarray, np.ndarray]:
        """The physical views of the whole pair (cached)."""
        if pair_id in self._views:
            self._views.move_to_end(pair_id)
            return self._views[pair_id]
        views = render_prior(self.prior, self.pair(pair_id))
        self._views[pair_id] = views
        self._bytes += sum(v.nbytes for v in views)
        while self._bytes > CACHE_BYTES and len(self._views) > 1:
            _, old = self._views.popitem(last=False)
            self._bytes -= sum(v.nbytes for v in old)
        return views

    def _crop_views(self, pair: Pair, y0: int, x0: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        H, W = pair.valid.shape
        if self.crop is None or H * W <= WHOLE_PAIR_AREA * max(h * w, 1):
            pl, pr = self.views(pair.params.pair_id)
            return pl[y0 : y0 + h, x0 : x0 + w], pr[y0 : y0 + h, x0 : x0 + w]
        coc = np.abs(pair.coc_px[pair.valid]) if pair.valid.any() else np.zeros(1)
        m = int(math.ceil(float(coc.max()) / 2)) + 16
        ya, xa, yb, xb = max(0, y0 - m), max(0, x0 - m), min(H, y0 + h + m), min(W, x0 + w + m)
        pl, pr = render_prior(self.prior, pair, (ya, xa, yb - ya, xb - xa))
        return pl[y0 - ya : y0 - ya + h, x0 - xa : x0 - xa + w], pr[y0 - ya : y0 - ya + h, x0 - xa : x0 - xa + w]

    def __getitem__(self, index: int) -> dict[str, object]:
        pair = self.pair(self.ids[index % len(self.ids)])
        rng = np.random.default_rng([self.seed, self.epoch, index])
        valid = pair.valid
        y0, x0, h, w = draw_crop(valid, self.crop, rng)
        sl = (slice(y0, y0 + h), slice(x0, x0 + w))
        pl, pr = self._crop_views(pair, y0, x0, h, w)
        p = pair.params
        (ox, oy), full = p.frame_geometry
        a = {"sharp": pair.sharp[sl], "left": pair.left[sl], "right": pair.right[sl], "prior_left": pl, "prior_right": pr,
             "coc_px": np.where(valid, pair.coc_px, 0).astype(np.float32)[sl],
             "depth_mm": np.where(valid, pair.depth_mm, 0).astype(np.float32)[sl], "valid": valid[sl]}
        field = frame_field((ox + x0, oy + y0), full, (w, h))
        fx, fy = p.focus_point_px[0] - x0, p.focus_point_px[1] - y0
        mirrored = False
        if self.crop is not None and self.crop.vflip and rng.random() < 0.5:
            a = {k: v[::-1] for k, v in a.items()}
            field = np.stack([field[0][::-1], -field[1][::-1]])
            fy = h - 1 - fy
        aug = self.augment
        if aug is not None and aug.hflip_swap > 0 and rng.random() < aug.hflip_swap:
            a = {k: v[:, ::-1] for k, v in a.items()}
            a["left"], a["right"] = a["right"], a["left"]
            a["prior_left"], a["prior_right"] = a["prior_right"], a["prior_left"]
            field = np.stack([-field[0][:, ::-1], field[1][:, ::-1]])
            fx = w - 1 - fx
            mirrored = True
        if aug is not None and aug.exposure > 0:
            g = float(np.exp(rng.uniform(-aug.exposure, aug.exposure)))
            for k in ("sharp", "left", "right", "prior_left", "prior_right"):
                a[k] = a[k] * np.float32(g)
        item: dict[str, object] = {k: _chw(v) for k, v in a.items()}
        item.update({
            "field": torch.from_numpy(np.ascontiguousarray(field)), "mirrored": torch.tensor(mirrored),
            "f_number": torch.tensor(p.f_number, dtype=torch.float32),
            "focus_distance_mm": torch.tensor(p.focus_distance_mm, dtype=torch.float32),
            "focal_length_mm": torch.tensor(p.focal_length_mm, dtype=torch.float32),
            "pixel_pitch_mm": torch.tensor(p.pixel_pitch_mm, dtype=torch.float32),
            "focus_point_px": torch.tensor([fx, fy], dtype=torch.float32),
            "sharp_f_number": torch.tensor(p.sharp_f_number, dtype=torch.float32), "pair_id": p.pair_id,
        })
        return item
