"""Score a trained deblurrer on a dataset split: masked MAE, PSNR and SSIM of its prediction against ``sharp``
(:mod:`dp5k_learn.metrics`), per pair and mean, beside the same metrics for the blurred input L + R (the floor a
deblurrer must beat), and a picture per pair (input L + R | prediction | sharp).

Writes into ``out`` (each file atomically): ``metrics.json``, ``table.md``, ``figures/<pair_id>.png``.
The mask is the pair's valid depth, or the whole image for a pair without depth (:func:`.train.target_mask`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from dp5k_common.errors import BadInputError
from dp5k_common.io import write_bytes_atomic, write_json_atomic
from dp5k_common.software import provenance
from dp5k_common.transfer import linear_to_srgb
from dp5k_learn.data import CropSpec, DPPairDataset, collate_dp

from .model import DPDeblurNet
from .train import load_deblurrer, sharp_metrics, views

METRICS = ("psnr", "ssim", "mae")
FIGURE_GAP_PX = 4
"""White gap between the three panels of a figure, px."""


@dataclass
class DeblurScores:
    """Per-pair and mean metrics of the prediction and of the blurred input (L + R), both against ``sharp``."""

    pairs: list[dict[str, Any]]
    mean: dict[str, dict[str, float]]

    def to_json(self) -> dict[str, Any]:
        return {"pairs": self.pairs, "mean": self.mean}


def figure(blurred: Tensor, pred: Tensor, sharp: Tensor) -> np.ndarray:
    """(H, 3 W + 2 gap, 3) uint8 sRGB picture: input L + R | prediction | sharp, from (3, H, W) linear images."""
    panels = [linear_to_srgb(np.clip(t.detach().float().cpu().numpy().transpose(1, 2, 0), 0, 1)) for t in (blurred, pred, sharp)]
    gap = np.ones((panels[0].shape[0], FIGURE_GAP_PX, 3), np.float32)
    strip = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1)
    return np.clip(np.rint(strip * 255), 0, 255).astype(np.uint8)


def write_figure(path: Path, picture: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
    if not ok:
        raise BadInputError("could not encode the figure as PNG", where=path)
    write_bytes_atomic(path, buf.tobytes())


@torch.no_grad()
def score(net: DPDeblurNet, dataset: str | os.PathLike[str], split: str = "test", device: str = "cpu",
          figures_dir: Path | None = None, max_pairs: int = 0) -> DeblurScores:
    """Metrics of ``net`` on every pair of ``dataset``'s ``split`` (whole images), figures when ``figures_dir``.

    Raises:
        EmptySplitError: the split is empty.
    """
    ds = DPPairDataset(dataset, split, CropSpec(), cache=False)
    n = len(ds.ids) if max_pairs <= 0 else min(max_pairs, len(ds.ids))
    net = net.to(device).eval()
    pairs: list[dict[str, Any]] = []
    for i in range(n):
        batch = collate_dp([ds[i]]).to(device)
        left, right = views(batch, str(dataset))
        pred = net(left, right).float()
        blurred = left + right
        row: dict[str, Any] = {"pair_id": batch.pair_ids[0]}
        for name, img in (("prediction", pred), ("input", blurred)):
            m = sharp_metrics(img, batch.sharp, batch.valid)
            row[name] = {k: float(m[k][0]) for k in METRICS}
        pairs.append(row)
        if figures_dir is not None:
            write_figure(figures_dir / f"{batch.pair_ids[0]}.png", figure(blurred[0], pred[0], batch.sharp[0]))
    mean = {name: {k: float(np.mean([p[name][k] for p in pairs])) for k in METRICS} for name in ("prediction", "input")}
    return DeblurScores(pairs, mean)


def table_md(scores: DeblurScores) -> str:
    """Markdown: one row per pair and the mean, prediction and input (L + R) side by side."""
    lines = ["| pair | PSNR pred (dB) | PSNR L+R (dB) | SSIM pred | SSIM L+R | MAE pred | MAE L+R |", "|---|---|---|---|---|---|---|"]
    for p in [*scores.pairs, {"pair_id": "**mean**", **scores.mean}]:
        a, b = p["prediction"], p["input"]
        lines.append(f"| {p['pair_id']} | {a['psnr']:.2f} | {b['psnr']:.2f} | {a['ssim']:.4f} | {b['ssim']:.4f} | "
                     f"{a['mae']:.4f} | {b['mae']:.4f} |")
    return "\n".join(lines) + "\n"


def evaluate_deblur(dataset: str | os.PathLike[str], checkpoint: str | os.PathLike[str], out: str | os.PathLike[str],
                    split: str = "test", device: str = "cpu", max_pairs: int = 0) -> DeblurScores:
    """``dp5k deblur evaluate``: score ``checkpoint`` on ``dataset``'s ``split``; write metrics.json, table.md, figures/.

    Raises:
        BadInputError: unusable checkpoint. EmptySplitError: empty split.
    """
    net = load_deblurrer(checkpoint, device)
    out = Path(out)
    scores = score(net, dataset, split, device, figures_dir=out / "figures", max_pairs=max_pairs)
    write_json_atomic(out / "metrics.json", {"dataset": str(dataset), "split": split, "checkpoint": str(checkpoint),
                                             "mask": "valid depth (whole image for pairs without depth)",
                                             "input": "the blurred input L + R", **scores.to_json(),
                                             "provenance": provenance()})
    write_bytes_atomic(out / "table.md", table_md(scores).encode())
    return scores
