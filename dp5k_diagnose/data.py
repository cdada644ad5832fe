"""Measured data for diagnosis, read only through dataset format v1: batches of pairs or crops with field maps."""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from dp5k_common.dataset import SHARP_F_NUMBER, DatasetReader, Pair
from dp5k_learn.batch import DPBatch
from neural_dp.registry import field_coords


@dataclass
class Sample:
    """A batch of pairs or crops and their field coordinates.

    Attributes:
        batch: the DPBatch (measured ``left``/``right`` set).
        field: (B, 2, H, W) field coordinates (x, y) in [-1, 1] of each full image.
        score: (B, 1, H, W) bool, the pixels fits and detection statistics count (:func:`predictable_mask`).
    """

    batch: DPBatch
    field: Tensor
    score: Tensor | None = None

    def __post_init__(self) -> None:
        if self.score is None:
            self.score = predictable_mask(self.batch)


BORDER_MARGIN_PX = 4.0
"""Pixels kept from the frame's (or crop's) border beyond the blur's reach: a view shifted against ``sharp``
(misregistration; the component fits up to 8 px) or resampled (a renderer's warp, a raw converter's
demosaic) carries content from outside the frame, or the warp's border fill, a few pixels in. On another
renderer's set with both views shifted by 1 px (cubic warp, reflected border) two fit crops each held one
such column at 1 px margin, 37 and 44 units of squared error against 0.1-0.5 for every other crop, which
hid a planted front/back asymmetry beside the misregistration."""


def predictable_mask(batch: DPBatch, margin_px: float = BORDER_MARGIN_PX, window_px: int = 17) -> Tensor:
    r"""(B, 1, H, W) bool: valid pixels whose value the sharp image inside the frame can predict.

    A view pixel collects light from sharp pixels up to half their blur diameter away; near the frame's
    (or crop's) border part of that light comes from scene content the sharp image does not show, so no
    model can predict it and its error would only dilute every statistic. Kept: valid pixels whose distance
    to the border (px) is at least :math:`\max_{w}|C| / 2 + \text{margin}` (:data:`BORDER_MARGIN_PX`), with :math:`\max_w |C|` the
    largest |signed CoC| (output px) in a ``window_px`` neighbourhood (neighbours' blur reaches the pixel too),
    and that no depth edge's blur reaches (:func:`occlusion_free_mask`). An image (or crop) where fewer than
    10 % of its valid pixels are far enough from the border keeps all of them (less those near depth edges).
    A pair (or crop) whose every such pixel is within a depth edge's reach scores none: a crop then adds
    nothing to the statistics, and a held-out pair is left out of the gain (:func:`gain.gain_report`).
    """
    B, _, H, W = batch.coc_px.shape
    a = batch.coc_px.abs() * batch.valid
    k = window_px | 1
    reach = torch.nn.functional.max_pool2d(a, k, stride=1, padding=k // 2) / 2 + margin_px
    ys = torch.arange(H, device=a.device, dtype=a.dtype)
    xs = torch.arange(W, device=a.device, dtype=a.dtype)
    dist = torch.minimum(torch.minimum(ys, H - 1 - ys)[:, None], torch.minimum(xs, W - 1 - xs)[None, :])
    keep = batch.valid & (dist >= reach)
    # an image whose blur nearly everywhere reaches past its border: score its valid pixels rather than none
    few = keep.flatten(1).sum(1) < 0.1 * batch.valid.flatten(1).sum(1)
    keep = torch.where(few.view(-1, 1, 1, 1), batch.valid, keep)
    return keep & occlusion_free_mask(batch)


def occlusion_free_mask(batch: DPBatch, min_jump_px: float = 0.5, rel_jump: float = 0.1, margin_px: float = 1.5) -> Tensor:
    r"""(B, 1, H, W) bool: pixels out of reach of every depth edge's blur.

    At a depth edge the views mix light from surfaces the RGBD input does not show (the background behind
    a blurred foreground's rim) and depend on how the two sides' blurs are composited, which no RGBD model
    knows: such pixels measure the occlusion model, not the lens. A depth edge is a pair of neighbouring
    pixels whose signed CoC differs by more than :math:`\max(\text{min\_jump}, \text{rel\_jump}
    \cdot \max|C|)` px; a pixel is dropped when it lies within :math:`\max|C|/2 + \text{margin}` px of one
    (square neighbourhoods, radii rounded up in steps of 25 %). Invalid pixels count as CoC 0, so the
    border of a region without depth is an edge as well.
    """
    c = torch.where(batch.valid, batch.coc_px[:, :1], torch.zeros_like(batch.coc_px[:, :1]))
    a = c.abs()
    dx, dy = (c[..., :, 1:] - c[..., :, :-1]).abs(), (c[..., 1:, :] - c[..., :-1, :]).abs()
    mx, my = torch.maximum(a[..., :, 1:], a[..., :, :-1]), torch.maximum(a[..., 1:, :], a[..., :-1, :])
    ex = dx > (rel_jump * mx).clamp(min=min_jump_px)  # invalid pixels count as CoC 0: their border is an edge too
    ey = dy > (rel_jump * my).clamp(min=min_jump_px)
    edge = torch.zeros_like(batch.valid)
    edge[..., :, 1:] |= ex
    edge[..., :, :-1] |= ex
    edge[..., 1:, :] |= ey
    edge[..., :-1, :] |= ey
    reach = torch.nn.functional.max_pool2d(a, 3, stride=1, padding=1) / 2 + margin_px
    near = torch.zeros_like(batch.valid)
    r = 2.0
    lower = 0.0
    while bool((edge & (reach > lower)).any()):
        sel = edge & (reach > lower) & (reach <= r)
        if bool(sel.any()):
            k = 2 * int(math.ceil(r)) + 1
            near |= torch.nn.functional.max_pool2d(sel.float(), k, stride=1, padding=k // 2) > 0
        lower, r = r, math.ceil(1.25 * r)
    return ~near


def load_pairs(reader: DatasetReader, ids: Sequence[str]) -> list[Pair]:
    return [reader.load(pid) for pid in ids]


def unstated_sharp_pairs(reader: DatasetReader, ids: Sequence[str]) -> frozenset[str]:
    """The pairs whose params.json does not state ``sharp_f_number`` (format v1 then reads 22)."""
    return frozenset(pid for pid in ids if "sharp_f_number" not in reader.params(pid).extra)


def read_sharp_at(samples: Sequence[Sample], f_number: float, pair_ids: frozenset[str]) -> list[Sample]:
    """The samples with ``sharp_f_number`` set to ``f_number`` (0 = all-in-focus) for the pairs in
    ``pair_ids``; other pairs keep theirs. Samples without any such pair are returned as they are."""
    out = []
    for s in samples:
        hit = [pid in pair_ids for pid in s.batch.pair_ids]
        if not any(hit):
            out.append(s)
            continue
        B = s.batch.sharp.shape[0]
        old = s.batch.sharp_f_number if s.batch.sharp_f_number is not None else torch.full((B,), SHARP_F_NUMBER)
        new = torch.where(torch.tensor(hit, device=old.device), torch.full_like(old, float(f_number)), old)
        out.append(Sample(replace(s.batch, sharp_f_number=new), s.field, s.score))
    return out


def full_samples(pairs: Sequence[Pair], device: str = "cpu", per_batch: int = 4) -> list[Sample]:
    """Whole pairs, grouped by image size, ``per_batch`` pairs per batch."""
    groups: dict[tuple[int, int], list[Pair]] = defaultdict(list)
    for p in pairs:
        groups[p.params.image_size].append(p)
    out = []
    for (W, H), ps in groups.items():
        for i in range(0, len(ps), per_batch):
            chunk = ps[i : i + per_batch]
            b = DPBatch.from_pairs(chunk, device)
            fields = [field_coords(1, H, W, device, *p.params.frame_geometry) for p in chunk]
            out.append(Sample(b, torch.cat(fields)))
    return out


CONTEXT_STEP_PX = 16
"""Context margins are rounded up to this step, so crops of pairs with similar blur share a shape (a batch)."""


def context_margin_px(p: Pair, crop: int) -> int:
    """Sharp-image context (px) a crop needs on each side: half the pair's largest blur diameter (99.9th
    percentile of valid |CoC|) plus 2 px, rounded up to :data:`CONTEXT_STEP_PX`, at most ``crop``."""
    a = np.abs(p.coc_px[p.valid])
    need = (float(np.quantile(a, 0.999)) / 2 if a.size else 0.0) + 2
    return int(min(math.ceil(need / CONTEXT_STEP_PX) * CONTEXT_STEP_PX, crop))


def crop_samples(
    pairs: Sequence[Pair], crop: int, crops_per_pair: int, rng: np.random.Generator, device: str = "cpu", per_batch: int = 8
) -> list[Sample]:
    """Random square crops (side ``crop`` px or the image, whichever is smaller) with full-image field maps.

    Each crop is the scored *core*; it is cut from the pair with :func:`context_margin_px` of extra sharp
    context on every side (as far as the image allows), so that the core's views can be predicted from
    the sharp image even where their blur reaches past the core (a 96 px core of a 640 px f/1.8 frame with
    100 px discs: without the context nearly no core pixel is predictable, and a crop's unpredictable
    pixels were once 6 x the systematic error of the other 15 detection crops together). Only the core's
    predictable pixels are scored (:func:`predictable_mask`). Small images (both sides <= ``crop``) are used
    whole, once.
    """
    items: list[tuple[DPBatch, Tensor, Tensor]] = []
    for p in pairs:
        W, H = p.params.image_size
        ch, cw = min(crop, H), min(crop, W)
        b = DPBatch.from_pairs([p], device)
        (ox, oy), full = p.params.frame_geometry
        n = 1 if (ch == H and cw == W) else crops_per_pair
        m = context_margin_px(p, crop) if (ch, cw) != (H, W) else 0
        eh, ew = min(ch + 2 * m, H), min(cw + 2 * m, W)  # the cut, core plus context
        for _ in range(n):
            y0 = int(rng.integers(0, H - ch + 1))
            x0 = int(rng.integers(0, W - cw + 1))
            Y0 = min(max(y0 - m, 0), H - eh)
            X0 = min(max(x0 - m, 0), W - ew)
            core = torch.zeros(1, 1, eh, ew, dtype=torch.bool, device=device)
            core[..., y0 - Y0 : y0 - Y0 + ch, x0 - X0 : x0 - X0 + cw] = True
            items.append((b.crop(Y0, X0, eh, ew), field_coords(1, eh, ew, device, (ox + X0, oy + Y0), full), core))
    groups: dict[tuple[int, int], list[tuple[DPBatch, Tensor, Tensor]]] = defaultdict(list)
    for b, f, c in items:
        groups[tuple(b.sharp.shape[-2:])].append((b, f, c))
    out = []
    for _, its in groups.items():
        for i in range(0, len(its), per_batch):
            chunk = its[i : i + per_batch]
            batch = cat_batches([c[0] for c in chunk])
            out.append(Sample(batch, torch.cat([c[1] for c in chunk]), predictable_mask(batch) & torch.cat([c[2] for c in chunk])))
    return out


def cat_batches(batches: Sequence[DPBatch]) -> DPBatch:
    """Concatenate same-size batches along the batch axis."""
    kw = {}
    for name in ("sharp", "coc_px", "depth_mm", "valid", "f_number", "focus_distance_mm", "focal_length_mm", "pixel_pitch_mm", "focus_point_px", "left", "right",
                 "sharp_f_number"):
        vals = [getattr(b, name) for b in batches]
        kw[name] = None if vals[0] is None else torch.cat(vals)
    kw["pair_ids"] = tuple(pid for b in batches for pid in b.pair_ids)
    return DPBatch(**kw)


SMALL_TRAIN_PAIRS = 8
"""A train split of at most this many pairs is fitted whole by ``--fit-pairs auto``; a larger one fits
:data:`DEFAULT_FIT_PAIRS` of its pairs (the atlas always reads every pair)."""
DEFAULT_FIT_PAIRS = 8
"""Fit pairs of ``--fit-pairs auto`` on a larger train split."""


def auto_fit_pairs(dataset: str | Path) -> int | None:
    """``--fit-pairs auto``: None (every train pair) where train has at most :data:`SMALL_TRAIN_PAIRS` pairs, else
    :data:`DEFAULT_FIT_PAIRS`."""
    return None if len(DatasetReader(dataset).ids("train")) <= SMALL_TRAIN_PAIRS else DEFAULT_FIT_PAIRS


@dataclass
class DiagnoseInput:
    """A dataset as one diagnosis reads it, once.

    Attributes:
        root: the dataset folder.
        reader: its reader (format v1).
        splits: ``fit`` (the train pairs whose crops fit the models), ``held`` (the held-out pairs the gains are
            measured on: test, else val, else train) and ``all`` (every pair, which the atlas reads), ids sorted.
        held_split: the split the held-out pairs come from.
        pairs: every pair, loaded, by id.
        full: one :class:`Sample` per pair (the whole image), by id.
        fit: the fit crops (several per batch).
        unstated: ids of the pairs whose params.json does not state ``sharp_f_number``.
    """

    root: Path
    reader: DatasetReader
    splits: dict[str, list[str]]
    held_split: str
    pairs: dict[str, Pair]
    full: dict[str, Sample]
    fit: list[Sample]
    unstated: frozenset[str]

    def samples(self, ids: Sequence[str]) -> list[Sample]:
        return [self.full[i] for i in ids]

    def read_sharp_at(self, f_number: float | None) -> "DiagnoseInput":
        """The input with ``sharp`` of the unstated pairs read at ``f_number`` (0 = all-in-focus; None: as is)."""
        if f_number is None or not self.unstated:
            return self
        full = {i: read_sharp_at([s], f_number, self.unstated)[0] for i, s in self.full.items()}
        return replace(self, full=full, fit=read_sharp_at(self.fit, f_number, self.unstated))


def read_input(dataset: str | Path, fit_pairs: int | None, crop_px: int, crops_per_pair: int, seed: int) -> DiagnoseInput:
    """Open ``dataset`` once and read every pair: the fit crops of (at most ``fit_pairs``) train pairs, one whole-image
    sample per pair.

    Raises:
        BadInputError: an empty train split, or too few pairs to hold any out.
    """
    from dp5k_common.errors import BadInputError

    reader = DatasetReader(dataset)
    train = reader.ids("train")
    val = reader.ids("val") if "val" in reader.splits else []
    test = reader.ids("test") if "test" in reader.splits else []
    if not train:
        raise BadInputError("the dataset's train split is empty; diagnose fits on train", where=reader.root)
    held_split = "test" if test else ("val" if val else "train")
    held = test or val or train
    rng = np.random.default_rng(seed)
    order = [train[i] for i in rng.permutation(len(train))]
    fit_ids = sorted(order[: len(order) if fit_pairs is None else fit_pairs])
    every = sorted(set(train) | set(val) | set(test))
    pairs = {pid: reader.load(pid) for pid in every}
    full = {pid: full_samples([pairs[pid]])[0] for pid in every}
    fit = crop_samples([pairs[pid] for pid in fit_ids], crop_px, crops_per_pair, rng)
    return DiagnoseInput(Path(dataset), reader, {"fit": fit_ids, "held": sorted(held), "all": every}, held_split, pairs, full,
                         fit, unstated_sharp_pairs(reader, every))
