"""Which pairs ``dp5k train`` learns from and which it validates on, and what a dataset is too small for.

A validation set must be data the network never trains on and that says something about data it has not seen:

* the dataset's **val split** when it has one (``dp5k import`` and ``dp5k process`` split by source capture, so its
  photos are not the train photos);
* else, with **several train source photos** (``params.json`` ``source_id``, else the scene), whole photos: a
  share (:attr:`~neural_dp.config.SelectConfig.holdout`, at least one) drawn with the run's seed;
* else, with **one train photo** cut into tiles (``dp5k import --tile``), **spatially separate tiles** of it: tile
  (row, column) of its grid is held out when ``(column - row) mod 4 = 1`` (a quarter of the tiles, one per row and
  column in every 4 x 4 block, spread over the field); the report says that they come from the photo the network
  trains on;
* else (one photo, whole frames: its cameras and f-numbers) a share of those pairs, with the same warning.

The test split is never used. A dataset that cannot give both sets (one pair), or whose train split has no pixel of
valid depth (a DPDD import), is refused before anything is written (:class:`~dp5k_common.errors.BadInputError`,
exit 3).
"""

from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dp5k_common.dataset import DatasetReader
from dp5k_common.errors import BadInputError, EmptySplitError

logger = logging.getLogger(__name__)

FEW_SOURCES = 3
"""Fewer train source photos than this draw a warning: the validation cannot see how the network does on other
photos (a single photo is one distance, one scene)."""


@dataclass
class Holdout:
    """The pairs a run trains on and validates on, and how they were chosen.

    Attributes:
        train: pair ids the network trains on.
        val: pair ids it is validated (and the physical model compared) on.
        how: one sentence on how ``val`` was chosen (goes into the run's report).
        kind: ``"val split"``, ``"photos"``, ``"tiles"`` or ``"pairs"``.
        train_sources: the source photos of ``train``.
        warnings: what the run's report and log warn about.
    """

    train: list[str]
    val: list[str]
    how: str
    kind: str
    train_sources: list[str]
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, object]:
        return {"train": self.train, "val": self.val, "how": self.how, "kind": self.kind,
                "train_sources": self.train_sources, "warnings": self.warnings}


def _tile_grid(reader: DatasetReader, ids: list[str]) -> dict[str, tuple[int, int]] | None:
    """(row, column) of each pair in its photo's tile grid, or None when the pairs are not tiles of one frame size."""
    origins = {}
    for pid in ids:
        p = reader.params(pid)
        if "crop_origin_px" not in p.extra:
            return None
        (x0, y0), _ = p.frame_geometry
        origins[pid] = (y0, x0)
    ys = sorted({o[0] for o in origins.values()})
    xs = sorted({o[1] for o in origins.values()})
    return {pid: (ys.index(y0), xs.index(x0)) for pid, (y0, x0) in origins.items()}


def plan_holdout(root: str | Path, fraction: float = 0.25, seed: int = 0) -> Holdout:
    """The train and validation pairs of ``root`` (module docstring).

    Raises:
        EmptySplitError: the train split is empty.
        BadInputError: nothing can be held out (a single pair and no val split), or no train pair has valid depth.
    """
    reader = DatasetReader(root)
    train = reader.ids("train")
    if not train:
        raise EmptySplitError("the train split is empty; nothing to train on", where=reader.root / "dataset.json")
    usable = [pid for pid in train if reader.params(pid).extra.get("has_depth", True) is not False]
    if not any(bool(reader.load(pid).valid.any()) for pid in usable):  # stops at the first pair with depth
        raise BadInputError(f"no train pair has a pixel of valid depth ({len(train)} pair(s)): the Neural DP Simulator "
                            "renders from depth and its loss is masked by it; nothing written", where=reader.root)
    by_source: dict[str, list[str]] = defaultdict(list)
    for pid in usable:
        by_source[reader.params(pid).source_id].append(pid)
    sources = sorted(by_source)
    warnings = []
    if len(usable) < len(train):
        warnings.append(f"{len(train) - len(usable)} train pair(s) without depth left out")
    val = reader.ids("val")
    if val:
        h = Holdout(usable, val, f"the dataset's val split ({len(val)} pairs)", "val split", sources, warnings)
    elif len(sources) >= 2:
        rng = np.random.default_rng(seed)
        n = min(len(sources) - 1, max(1, int(round(fraction * len(sources)))))
        held = sorted(rng.choice(sources, size=n, replace=False).tolist())
        h = Holdout([p for s in sources if s not in held for p in by_source[s]], [p for s in held for p in by_source[s]],
                    f"{n} of the {len(sources)} train photos held out ({', '.join(held)}): no val split", "photos",
                    [s for s in sources if s not in held], warnings)
    else:
        only = by_source[sources[0]]
        if len(only) < 2:
            raise BadInputError(f"one photo ({sources[0]}) as one pair: nothing to validate on, so nothing would show "
                                "whether a network beats the physical model; import it in tiles (dp5k import --tile WxH) "
                                "or add photos; nothing written", where=reader.root)
        grid = _tile_grid(reader, only)
        if grid is not None:
            held = [p for p in only if (grid[p][1] - grid[p][0]) % 4 == 1] or only[1::4]
            if len(held) == len(only):
                held = held[:-1]
            h = Holdout([p for p in only if p not in held], held,
                        f"{len(held)} of the {len(only)} tiles of the one train photo {sources[0]} held out, spatially "
                        "separate from the train tiles (tile (row, col) with (col - row) mod 4 = 1): they show the same "
                        "photo, so the validation cannot see other distances or scenes", "tiles", sources, warnings)
        else:
            held = only[1::4] or only[-1:]
            h = Holdout([p for p in only if p not in held], held,
                        f"{len(held)} of the {len(only)} pairs of the one train photo {sources[0]} held out (its other "
                        "cameras or f-numbers, not separate photos)", "pairs", sources, warnings)
    if len(h.train_sources) < FEW_SOURCES:
        h.warnings.append(f"the train set is {len(h.train_sources)} photo(s) ({', '.join(h.train_sources)}), "
                          f"{len(h.train)} pairs: too few to show how a learned correction does on other photos; "
                          f"validation: {h.how}")
    return h
