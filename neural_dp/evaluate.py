"""Table 2: every simulator on the same pairs, masked MAE / PSNR / SSIM, invalid depth masked out.

``evaluate(...)`` runs each simulator on every pair of a split at full resolution, averages the three
masked metrics over the left and right views per pair and then over pairs (the paper's protocol), and
writes into ``out_dir``:

* ``metrics.json``: per simulator the means, plus every pair's numbers and the run's settings;
* ``table.md``: the Markdown table (rows MAE / PSNR / SSIM, one column per simulator, best in bold);
* ``figures/<pair_id>.png``: for the first pairs, the measured views and each simulator's views with
  their absolute-error maps side by side (invalid depth painted black, as the paper's Fig. 10).

Simulators with free parameters (the physical base model) are first fitted on training pairs
(``DPSimulator.fit``); the peers keep their published defaults.

An interrupted run resumes: after each pair its numbers go to ``OUT/.evaluate-progress.json``; a run with the same
settings into the same OUT fits again (deterministic), keeps those pairs and scores the rest (when the fit differs it
starts over). A finished run is replaced.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dp5k_common.dataset import DatasetReader
from dp5k_common.errors import BadInputError, EmptySplitError
from dp5k_common.io import atomic_path, write_json_atomic
from dp5k_common.progress import progress
from dp5k_common.run_progress import RunProgress, canonical
from dp5k_common.software import provenance
from dp5k_learn.batch import DPBatch
from dp5k_learn.data import CropSpec, DPPairDataset, collate_dp
from dp5k_learn.distributed import resolve_device
from dp5k_learn.metrics import view_metrics

from .simulators.catalog import SimulatorSpec, default_simulators
from .simulators.interface import DPSimulator

logger = logging.getLogger(__name__)

PROGRESS_FILE = ".evaluate-progress.json"
"""In OUT while an evaluation runs: its settings and every scored pair's numbers (what a rerun continues from)."""
TITLES = {"disk": "Translating disk", "butterworth": "Butterworth", "raytrace": "Ray tracing",
          "base": "Physical base", "neural": "Neural DP", "diagnosed": "Diagnosed"}


@dataclass
class EvalResult:
    """Means per simulator (``{"disk": {"mae", "psnr", "ssim", "pairs", "seconds"}, ...}``) and the files written."""

    means: dict[str, dict[str, float]]
    out_dir: Path
    table_md: str


def _fit_batches(root: Path, n_pairs: int, crop_px: int, device: torch.device) -> list[DPBatch]:
    try:
        ds = DPPairDataset(root, "train", CropSpec(crop_px, vflip=False), seed=0)
    except EmptySplitError:  # nothing to fit on: the simulators keep their published defaults
        return []
    return [collate_dp([ds[i]]).to(device) for i in range(min(n_pairs, len(ds.ids)))]


def column_names(specs: Sequence[SimulatorSpec]) -> list[str]:
    """Each spec's column: the simulator's name, or the whole spec where two specs share a name (two checkpoints).

    Raises:
        BadInputError: the same spec twice.
    """
    texts = [str(s) for s in specs]
    if len(set(texts)) < len(texts):
        raise BadInputError(f"a simulator is named twice: {', '.join(texts)}", where="--simulator")
    names = [s.name for s in specs]
    return [s.name if names.count(s.name) == 1 else str(s) for s in specs]


def _overrides_fit(sim: DPSimulator) -> bool:
    return type(sim).fit is not DPSimulator.fit


def markdown_table(means: dict[str, dict[str, float]]) -> str:
    """Table 2 layout: metrics as rows, simulators as columns; the best value of each row in bold."""
    names = list(means)
    header = "| | " + " | ".join(TITLES.get(n, n) for n in names) + " |"
    lines = [header, "|---|" + "---|" * len(names)]
    for key, label, fmt, better in (("mae", "MAE", "{:.4f}", min), ("psnr", "PSNR (dB)", "{:.2f}", max),
                                    ("ssim", "SSIM", "{:.4f}", max)):
        vals = [means[n][key] for n in names]
        finite = [v for v in vals if np.isfinite(v)]
        best = better(finite) if finite else None
        cells = [("**" + fmt.format(v) + "**") if v == best else fmt.format(v) for v in vals]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _display(img: Tensor) -> np.ndarray:
    """(3, H, W) linear -> (H, W, 3) gamma 1/2.2 for viewing, clipped to [0, 1]."""
    return np.clip(img.detach().float().cpu().numpy().transpose(1, 2, 0), 0, 1) ** (1 / 2.2)


def save_figure(path: Path, batch: DPBatch, views: dict[str, tuple[Tensor, Tensor]]) -> None:
    """Rows: measured, then each simulator; columns: left, right, |left error|, |right error|."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    valid = batch.valid[0, 0].cpu().numpy()
    rows = [("measured", (batch.left, batch.right))] + list(views.items())
    H, W = valid.shape
    fig, axes = plt.subplots(len(rows), 4, figsize=(4 * 2.6, len(rows) * 2.6 * H / W + 0.4), squeeze=False)
    assert batch.left is not None and batch.right is not None
    vmax = 0.1
    for r, (name, (left, right)) in enumerate(rows):
        for c, img in enumerate((left, right)):
            show = _display(img[0]) * valid[..., None]
            axes[r, c].imshow(show)
        for c, (pred, gt) in enumerate(((left, batch.left), (right, batch.right))):
            err = (pred[0] - gt[0]).abs().mean(0).cpu().numpy() * valid
            axes[r, 2 + c].imshow(err, cmap="magma", vmin=0, vmax=vmax)
        axes[r, 0].set_ylabel(TITLES.get(name, name), fontsize=8)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    for c, title in enumerate(("left", "right", f"|left err| (0..{vmax})", f"|right err| (0..{vmax})")):
        axes[0, c].set_title(title, fontsize=8)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def evaluate(dataset: str | os.PathLike[str], out_dir: str | os.PathLike[str], *, split: str = "test",
             simulators: Sequence[SimulatorSpec | str] | None = None, checkpoint: str | os.PathLike[str] | None = None,
             device: str = "cpu", max_pairs: int = 0, figures: int = 2, fit_pairs: int = 8,
             fit_crop_px: int = 256) -> EvalResult:
    """Compare simulators on one split (see module docstring).

    Args:
        dataset: format-v1 dataset.
        out_dir: output folder (created).
        split: which split to evaluate.
        simulators: specs, or their text (``disk``, ..., ``neural:CKPT``, ``diagnosed:REPORT.json``); default: the
            peers, the base model and, with ``checkpoint``, the Neural DP Simulator. Each is a column named by
            the simulator (its whole spec where two share a name).
        checkpoint: the Neural DP checkpoint (``best.pt`` written by ``dp5k train``) of a bare ``neural``.
        device: torch device for the simulators, or ``auto`` (the first CUDA GPU, else the CPU).
        max_pairs: evaluate at most this many pairs (0 = all).
        figures: how many pairs get a comparison picture.
        fit_pairs / fit_crop_px: training crops given to simulators with free parameters.

    Raises:
        EmptySplitError: the split to evaluate is empty.
        BadInputError: unknown simulator, ``neural`` without a checkpoint, a missing checkpoint or report.
    """
    root, out = Path(dataset), Path(out_dir)
    reader = DatasetReader(root)
    ids = reader.ids(split)
    if max_pairs > 0:
        ids = ids[:max_pairs]
    if not ids:
        raise EmptySplitError(f"split '{split}' has no pairs to evaluate", where=root / "dataset.json")
    if simulators:
        specs = [s if isinstance(s, SimulatorSpec) else SimulatorSpec.parse(s, checkpoint) for s in simulators]
    else:
        specs = default_simulators(checkpoint)
    for spec in specs:
        spec.check_files()
    names = column_names(specs)
    dev = resolve_device(device)
    sims: dict[str, DPSimulator] = {}
    fitted: dict[str, dict[str, float]] = {}
    fit_batches: list[DPBatch] | None = None
    for name, spec in zip(names, specs):
        sim = spec.load().to(dev)
        sim.eval()
        if _overrides_fit(sim):
            if fit_batches is None:
                fit_batches = _fit_batches(root, fit_pairs, fit_crop_px, dev)
            if fit_batches:
                fitted[name] = {k: float(v) for k, v in sim.fit(fit_batches).items()}
        sims[name] = sim
    ds = DPPairDataset(root, split, CropSpec(), cache=False)
    index = {pid: i for i, pid in enumerate(ds.ids)}
    per_pair: dict[str, dict[str, dict[str, float]]] = {}
    seconds = {n: 0.0 for n in names}
    no_depth: list[str] = []
    prog = RunProgress(out / PROGRESS_FILE, {"dataset": str(root.resolve()), "split": split, "pairs": ids,
                                             "specs": [str(spec) for spec in specs], "columns": names,
                                             "fit_pairs": fit_pairs, "fit_crop_px": fit_crop_px, "device": str(dev)})
    earlier = prog.earlier()
    if earlier is not None:
        if earlier.get("fitted") == canonical(fitted):
            per_pair, no_depth, seconds = earlier["per_pair"], earlier["no_depth"], earlier["seconds"]
            logger.info("%s: resuming an interrupted evaluation, %d of %d pairs done", out, len(per_pair) + len(no_depth),
                        len(ids))
        else:
            logger.warning("%s: the fit differs from the interrupted evaluation's; scoring every pair again", out)
    out.mkdir(parents=True, exist_ok=True)
    todo = [(k, pid) for k, pid in enumerate(ids) if pid not in per_pair and pid not in no_depth]
    for k, pid in progress(todo, desc=f"evaluate {split}", unit="pair"):
        batch = collate_dp([ds[index[pid]]]).to(dev)
        if not bool(batch.valid.any()):  # e.g. a DPDD import: the simulators render from depth, metrics mask by it
            no_depth.append(pid)
            prog.save({"fitted": fitted, "per_pair": per_pair, "no_depth": no_depth, "seconds": seconds})
            continue
        views: dict[str, tuple[Tensor, Tensor]] = {}
        per_pair[pid] = {}
        for name, sim in sims.items():
            t0 = time.perf_counter()
            with torch.no_grad():
                left, right = sim(batch)
            seconds[name] += time.perf_counter() - t0
            left, right = left.float(), right.float()
            m = view_metrics(left, right, batch.left, batch.right, batch.valid)
            per_pair[pid][name] = {key: float(v[0]) for key, v in m.items()}
            views[name] = (left, right)
        if k < figures:
            save_figure(out / "figures" / f"{pid}.png", batch, views)
        prog.save({"fitted": fitted, "per_pair": per_pair, "no_depth": no_depth, "seconds": seconds})
    scored = [p for p in ids if p in per_pair]
    if not scored:
        raise BadInputError(f"no pair of split '{split}' has valid depth (a DPDD import has none): the simulators render "
                            "from depth and the metrics are masked by it", where=root / "dataset.json")
    if no_depth:
        logger.warning("%s: %d pair(s) without valid depth left out: %s", root, len(no_depth), ", ".join(no_depth[:5]))
    means: dict[str, dict[str, float]] = {}
    for name in names:
        vals = {key: [per_pair[p][name][key] for p in scored] for key in ("mae", "psnr", "ssim")}
        means[name] = {key: float(np.nanmean(v)) for key, v in vals.items()}
        means[name]["pairs"] = float(len(scored))
        means[name]["seconds_per_pair"] = seconds[name] / len(scored)
    table = markdown_table(means)
    report: dict[str, Any] = {
        "dataset": str(root), "split": split, "pairs": scored, "pairs_without_depth": no_depth, "simulators": names,
        "specs": [str(spec) for spec in specs],
        "checkpoint": next((str(spec.checkpoint) for spec in specs if spec.is_neural), None), "device": str(dev),
        "metric_definitions": "masked MAE/PSNR/SSIM (dp5k_learn.metrics), mean of left and right view, mean over pairs",
        "fitted_parameters": fitted, "fit_pairs": len(fit_batches or []), "means": means, "per_pair": per_pair,
        "provenance": provenance(),
    }
    write_json_atomic(out / "metrics.json", report)
    with atomic_path(out / "table.md") as tmp:
        tmp.write_text(f"Split '{split}' of {root.name}, {len(scored)} pairs"
                       + (f" ({len(no_depth)} without valid depth left out)" if no_depth else "") + ".\n\n" + table)
    prog.finish()
    return EvalResult(means, out, table)
