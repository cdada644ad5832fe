"""A torch ``Dataset`` over a format-v1 dataset split, with deterministic random crops for training."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from dp5k_common.dataset import DatasetReader, Pair
from dp5k_common.errors import EmptySplitError

from .batch import DPBatch, frame_field


@dataclass(frozen=True)
class CropSpec:
    """How training items are cut from pairs."""

    size_px: int = 0
    """Side of the square random crop; 0 = the whole image."""
    min_valid_fraction: float = 0.8
    """A crop is redrawn (up to ``tries`` times) unless this much of its depth is valid (the released code: 80 %)."""
    tries: int = 10
    vflip: bool = False
    """Random vertical flip with p = 0.5 (the released code's augmentation; keeps horizontal DP disparity)."""


def _to_tensor(img: np.ndarray) -> Tensor:
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1) if img.ndim == 3 else img[None]))


def draw_crop(valid: np.ndarray, crop: CropSpec | None, rng: np.random.Generator) -> tuple[int, int, int, int]:
    """(y0, x0, h, w) px of a training crop of a pair whose depth-valid mask is ``valid`` (H, W): the whole pair when
    ``crop`` is None or no smaller than it, else a square of ``crop.size_px`` (clipped to the pair) drawn until at
    least ``crop.min_valid_fraction`` of it is valid, at most ``crop.tries`` times (the last draw is kept)."""
    H, W = valid.shape
    if crop is None or not crop.size_px or (crop.size_px >= H and crop.size_px >= W):
        return 0, 0, H, W
    h, w = min(crop.size_px, H), min(crop.size_px, W)
    y0 = x0 = 0
    for _ in range(max(1, crop.tries)):
        y0 = int(rng.integers(0, H - h + 1))
        x0 = int(rng.integers(0, W - w + 1))
        if valid[y0 : y0 + h, x0 : x0 + w].mean() >= crop.min_valid_fraction:
            break
    return y0, x0, h, w


class DPPairDataset(Dataset):
    """Items of one split: a dict of tensors for one (possibly cropped) pair.

    Args:
        root: dataset folder.
        split: "train", "val" or "test".
        crop: crop specification (whole images by default).
        seed: base seed; item ``i`` of epoch ``e`` draws its crop from ``(seed, e, i)`` only, so the data a
            step sees never depends on worker count, rank layout or resumption.
        length: items per epoch (0 = the number of pairs); with random crops an epoch may revisit pairs.
        cache: keep loaded pairs in memory (small datasets).
        ids: serve these pairs of ``split`` only (e.g. a validation subset a trainer held out); default all.

    Item keys: sharp, left, right (3, h, w); coc_px, depth_mm (1, h, w), 0 where invalid; valid (1, h, w) bool;
    f_number, focus_distance_mm, focal_length_mm, pixel_pitch_mm (scalars); focus_point_px (2,); pair_id; field
    (2, h, w), the pixels' field coordinates in their camera frame (:func:`~dp5k_learn.batch.frame_field`).
    """

    def __init__(self, root: str | os.PathLike[str], split: str, crop: CropSpec | None = None, seed: int = 0,
                 length: int = 0, cache: bool = True, ids: list[str] | None = None) -> None:
        self.reader = DatasetReader(root)
        self.ids = self.reader.ids(split)
        if ids is not None:
            unknown = sorted(set(ids) - set(self.ids))
            if unknown:
                raise EmptySplitError(f"pairs not in split '{split}': {', '.join(unknown[:3])}", where=self.reader.root / "dataset.json")
            self.ids = list(ids)
        if not self.ids:
            raise EmptySplitError(f"split '{split}' is empty", where=self.reader.root / "dataset.json")
        self.split = split
        self.crop = crop or CropSpec()
        self.seed = seed
        self.length = length or len(self.ids)
        self.epoch = 0
        self._cache: dict[str, Pair] | None = {} if cache else None

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch whose crops ``__getitem__`` draws."""
        self.epoch = epoch

    def __len__(self) -> int:
        return self.length

    def pair(self, pair_id: str) -> Pair:
        if self._cache is None:
            return self.reader.load(pair_id)
        if pair_id not in self._cache:
            self._cache[pair_id] = self.reader.load(pair_id)
        return self._cache[pair_id]

    def __getitem__(self, index: int) -> dict[str, object]:
        pair = self.pair(self.ids[index % len(self.ids)])
        rng = np.random.default_rng([self.seed, self.epoch, index])
        valid = pair.valid
        H, W = valid.shape
        y0, x0, h, w = draw_crop(valid, self.crop, rng)
        sl = (slice(y0, y0 + h), slice(x0, x0 + w))
        flip = bool(self.crop.vflip and rng.random() < 0.5)

        def cut(a: np.ndarray) -> Tensor:
            a = a[sl]
            return _to_tensor(a[::-1] if flip else a)

        p = pair.params
        fy = (H - 1 - p.focus_point_px[1]) if flip else p.focus_point_px[1]
        (ox, oy), full = p.frame_geometry
        field = frame_field((ox + x0, oy + y0), full, (w, h))
        if flip:
            field = np.stack([field[0][::-1], -field[1][::-1]])  # rows reversed: y mirrored about the frame centre
        return {
            "sharp": cut(pair.sharp),
            "left": cut(pair.left),
            "right": cut(pair.right),
            "coc_px": cut(np.where(valid, pair.coc_px, 0).astype(np.float32)),
            "depth_mm": cut(np.where(valid, pair.depth_mm, 0).astype(np.float32)),
            "valid": cut(valid),
            "f_number": torch.tensor(p.f_number, dtype=torch.float32),
            "focus_distance_mm": torch.tensor(p.focus_distance_mm, dtype=torch.float32),
            "focal_length_mm": torch.tensor(p.focal_length_mm, dtype=torch.float32),
            "pixel_pitch_mm": torch.tensor(p.pixel_pitch_mm, dtype=torch.float32),
            "focus_point_px": torch.tensor([p.focus_point_px[0] - x0, fy - y0], dtype=torch.float32),
            "sharp_f_number": torch.tensor(p.sharp_f_number, dtype=torch.float32),
            "pair_id": p.pair_id,
            "field": torch.from_numpy(np.ascontiguousarray(field)),
        }


def collate_dp(items: list[dict[str, object]]) -> DPBatch:
    """Stack dataset items (all of one size) into a :class:`DPBatch` on the CPU. The optional keys ``field``,
    ``prior_left``, ``prior_right`` and ``mirrored`` fill the batch's fields of those names when every item has them."""
    def stack(key: str) -> Tensor:
        return torch.stack([it[key] for it in items])  # type: ignore[misc]

    def optional(key: str) -> Tensor | None:
        return stack(key) if all(key in it for it in items) else None

    return DPBatch(
        sharp=stack("sharp"), coc_px=stack("coc_px"), depth_mm=stack("depth_mm"), valid=stack("valid"),
        f_number=stack("f_number"), focus_distance_mm=stack("focus_distance_mm"),
        focal_length_mm=stack("focal_length_mm"), pixel_pitch_mm=stack("pixel_pitch_mm"),
        focus_point_px=stack("focus_point_px"), left=stack("left"), right=stack("right"),
        pair_ids=tuple(str(it["pair_id"]) for it in items), sharp_f_number=stack("sharp_f_number"),
        field=optional("field"), prior_left=optional("prior_left"), prior_right=optional("prior_right"),
        mirrored=optional("mirrored"),
    )
