"""Diagnose the Neural DP Simulator's reach and extend it: error against |CoC|, multi-scale kernels, gain per bin.

The paper's simulator predicts 5 x 5 per-pixel kernels plus additive residuals, so a blur disc wider than the
kernel (reach 2 px) must be faked by the residual images, and the error grows with |CoC|. The structural
change that addresses it is multi-scale kernel prediction (``ModelConfig.multiscale_levels``,
:func:`neural_dp.model.extend_multiscale`): the network also predicts K x K kernels applied at dilations
2, 4, ... to a box-prefiltered image (taps that tile a ``K d``-px square), blended per pixel.

:func:`diagnose_neural` takes a trained checkpoint and:

1. measures its masked error on the held-out split (test, else val) per |CoC| bin (before);
2. extends the loaded network with multi-scale kernels, initialised so that its output equals the
   checkpoint's exactly (zero blend weights; checked and reported), and fine-tunes it on train crops for a
   fixed number of steps (extended);
3. fine-tunes the unextended checkpoint with the same data, order, optimiser, loss mask and budget
   (control), so the gain is the structure's, not the extra training's;
4. reports masked PSNR / SSIM / MAE (``neural_dp.metrics``) before / control / extended, per-|CoC|-bin PSNR of
   all three, the per-bin PSNR gain of extended over control with a bootstrap CI over pairs
   (:func:`dp5k_diagnose.gain.bootstrap_ci`), and writes ``neural_reach.png`` (error vs |CoC|, gain per bin),
   ``neural_reach.json`` and the two fine-tuned checkpoints (``control.pt``, ``extended.pt``; both load with
   ``get_simulator("neural", checkpoint=...)``).

Usage: ``python -m dp5k_diagnose.neural_reach DATASET CKPT OUT [--steps N] [--levels L] [--seed S] [--device D]``.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dp5k_common.dataset import DatasetReader
from dp5k_common.errors import BadInputError
from dp5k_common.io import atomic_path, write_json_atomic
from dp5k_common.progress import progress
from neural_dp.checkpoint import save_checkpoint
from neural_dp.data import CropSpec, DPPairDataset, collate_dp
from neural_dp.losses import dp_loss
from neural_dp.model import extend_multiscale
from neural_dp.simulators.neural import NeuralDPSimulator, model_inputs
from neural_dp.train import loss_mask

from .data import Sample, full_samples, load_pairs
from .gain import bootstrap_ci, gain_report, pair_metrics

BINS_PX: tuple[float, ...] = (0.0, 2.0, 4.0, 8.0, 16.0, 32.0, math.inf)
"""|CoC| bin edges in px (the last bin is open)."""
MIN_BIN_PX = 50
"""A pair contributes to a bin's PSNR only with at least this many valid pixels in it."""

Predict = Callable[[Sample], tuple[Tensor, Tensor]]


@dataclass
class BinErrors:
    """Masked errors of L and R together per pair and |CoC| bin, arrays (n_pairs, n_bins).

    Attributes:
        pair_ids: the pairs, in row order.
        sse: sum of squared errors over the bin's valid pixels, 3 channels and both views (linear units^2).
        sae: sum of absolute errors, same pixels.
        count: number of terms in the sums (pixels x 3 channels x 2 views).
        psnr: per-pair PSNR in dB of the bin's MSE (data range 1); NaN with fewer than ``MIN_BIN_PX`` pixels.
        sse_ref: the same sum for the no-blur reference (each view = the sharp image times the pair's mean
            view / sharp ratio per channel): how much defocus signal the bin holds, to normalise by.
    """

    pair_ids: list[str]
    sse: np.ndarray
    sae: np.ndarray
    count: np.ndarray
    psnr: np.ndarray
    sse_ref: np.ndarray

    def unexplained(self) -> np.ndarray:
        """(n_bins,) pooled SSE over the no-blur reference's SSE: the fraction of the defocus signal left."""
        r = self.sse_ref.sum(0)
        return np.where(r > 0, self.sse.sum(0) / np.maximum(r, 1e-30), np.nan)

    def pooled_mse(self) -> np.ndarray:
        """(n_bins,) MSE over all pairs' pixels in each bin (NaN where empty)."""
        c = self.count.sum(0)
        return np.where(c > 0, self.sse.sum(0) / np.maximum(c, 1), np.nan)

    def pooled_mae(self) -> np.ndarray:
        """(n_bins,) MAE over all pairs' pixels in each bin (NaN where empty)."""
        c = self.count.sum(0)
        return np.where(c > 0, self.sae.sum(0) / np.maximum(c, 1), np.nan)


def bin_errors(predict: Predict, samples: Sequence[Sample], bins: Sequence[float] = BINS_PX,
               min_px: int = MIN_BIN_PX) -> BinErrors:
    """Masked error of a simulator's views per pair and |CoC| bin (views clamped to [0, 1], as the metrics).

    Args:
        predict: ``predict(sample) -> (left, right)``, each (B, 3, H, W).
        samples: held-out batches with measured views.
        bins: increasing |CoC| edges in px; bin j is ``bins[j] <= |CoC| < bins[j + 1]``.
        min_px: fewest valid pixels for a pair's per-bin PSNR.

    Returns:
        A :class:`BinErrors`.
    """
    ids: list[str] = []
    sse, sae, cnt, ref = [], [], [], []
    edges = list(bins)
    with torch.no_grad():
        for s in samples:
            left, right = predict(s)
            b = s.batch
            d_l = left.clamp(0, 1) - b.left
            d_r = right.clamp(0, 1) - b.right
            e2 = (d_l**2 + d_r**2).sum(1)  # (B, H, W), 6 terms per pixel
            e1 = (d_l.abs() + d_r.abs()).sum(1)
            vf = b.valid.to(b.sharp.dtype)
            den = (b.sharp * vf).sum((2, 3), keepdim=True).clamp_min(1e-12)
            g_l, g_r = (b.left * vf).sum((2, 3), keepdim=True) / den, (b.right * vf).sum((2, 3), keepdim=True) / den
            e2_ref = ((g_l * b.sharp - b.left) ** 2 + (g_r * b.sharp - b.right) ** 2).sum(1)
            a = b.coc_px[:, 0].abs()
            v = b.valid[:, 0]
            for lo, hi in zip(edges[:-1], edges[1:]):
                m = (v & (a >= lo) & (a < hi)).to(e2.dtype)
                sse.append((e2 * m).sum((1, 2)).double().cpu().numpy())
                sae.append((e1 * m).sum((1, 2)).double().cpu().numpy())
                cnt.append((6.0 * m.sum((1, 2))).double().cpu().numpy())
                ref.append((e2_ref * m).sum((1, 2)).double().cpu().numpy())
            ids += list(b.pair_ids)
    nb = len(edges) - 1
    # sse was appended per (sample, bin); regroup to (pairs, bins).
    def stack(parts: list[np.ndarray]) -> np.ndarray:
        rows = [np.stack(parts[i : i + nb], axis=1) for i in range(0, len(parts), nb)]
        return np.concatenate(rows, axis=0) if rows else np.zeros((0, nb))

    S, A, C = stack(sse), stack(sae), stack(cnt)
    with np.errstate(divide="ignore", invalid="ignore"):
        mse = S / C
        psnr = np.where(C / 6.0 >= min_px, 10.0 * np.log10(1.0 / np.maximum(mse, 1e-20)), np.nan)
    return BinErrors(ids, S, A, C, psnr, stack(ref))


def _resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def finetune(sim: NeuralDPSimulator, dataset: str | Path, steps: int, *, seed: int = 0, lr: float = 5e-4,
             crop_px: int = 96, batch_size: int = 4, border_px: int | None = None, grad_clip: float = 1.0,
             grad_weight: float = 1.0, new_lr_mult: float = 1.0, device: torch.device | str = "cpu",
             desc: str = "fine-tune") -> list[float]:
    """Fine-tune a Neural DP Simulator in place on train crops for exactly ``steps`` Adam steps.

    The crops and their order depend only on ``seed`` (and the dataset), so two calls with the same
    arguments see identical batches: the control and the extension are trained on the same data.
    Adam with cosine annealing from ``lr`` to 0, the training loss of Eq. 8 on the valid mask minus a
    ``border_px`` frame (default: the network's kernel reach), global gradient clipping.

    Args:
        sim: the simulator to train (its ``net`` is updated in place, left in eval mode).
        dataset: a format-v1 dataset with a non-empty train split.
        steps: optimiser steps.
        seed: data-order / crop / dropout seed.
        lr: peak learning rate.
        crop_px: side of the square random crops (0 = whole images).
        batch_size: crops per step.
        border_px: loss border in px.
        grad_clip: global gradient norm clip (0 = off).
        grad_weight: weight of the gradient terms of the loss.
        new_lr_mult: learning-rate factor of the multi-scale head (the parameters the extension adds; they
            start at zero blend and need to travel further than the trained ones). No effect on a
            single-scale network.
        device: where to train.
        desc: progress-bar label.

    Returns:
        The loss of every step (length ``steps``).
    """
    device = torch.device(device)
    ds = DPPairDataset(dataset, "train", CropSpec(crop_px, vflip=False), seed=seed, length=max(1, steps * batch_size))
    order = np.random.default_rng(seed).permutation(len(ds))
    border = sim.net.reach_px if border_px is None else int(border_px)
    sim.to(device)
    new = [p for n, p in sim.net.named_parameters() if n.startswith("scale_head.")]
    old = [p for n, p in sim.net.named_parameters() if not n.startswith("scale_head.")]
    groups = [{"params": old, "lr": lr}] + ([{"params": new, "lr": lr * new_lr_mult}] if new else [])
    opt = torch.optim.Adam(groups, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, steps), eta_min=0.0)
    torch.manual_seed(seed)
    sim.train()
    losses: list[float] = []
    for k in progress(range(steps), desc=desc, unit="step"):
        idx = order[(k * batch_size) % len(ds) :][:batch_size]
        batch = collate_dp([ds[int(i)] for i in idx]).to(device)
        left, right = sim.net(batch.sharp, model_inputs(batch, sim.cfg.coc_scale_px))
        loss = dp_loss(left, right, batch.left, batch.right, loss_mask(batch.valid, border), grad_weight)
        if not torch.isfinite(loss):
            raise BadInputError(f"fine-tuning loss is {float(loss)} at step {k} (lower lr?)", where="finetune")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(sim.net.parameters(), grad_clip)
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
    sim.eval()
    return losses


def _nan_to_none(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_nan_to_none(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def _spearman(x: np.ndarray, y: np.ndarray) -> float:
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 2:
        return float("nan")
    rx = np.argsort(np.argsort(x[ok])).astype(float)
    ry = np.argsort(np.argsort(y[ok])).astype(float)
    if rx.std() == 0 or ry.std() == 0:
        return float("nan")
    return float(np.corrcoef(rx, ry)[0, 1])


def _bin_label(lo: float, hi: float) -> str:
    return f">= {lo:g}" if not math.isfinite(hi) else f"{lo:g}-{hi:g}"


def plot_reach(res: dict[str, Any], path: Path) -> str:
    """Two panels: pooled RMSE per |CoC| bin before / control / extended, and the per-bin PSNR gain with CIs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in res["per_bin"] if r["pixels"] > 0]
    labels = [_bin_label(r["bin_px"][0], math.inf if r["bin_px"][1] is None else r["bin_px"][1]) + f"\n{r['n_pairs']} pairs"
              for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    ax = axes[0]
    for key, name, mk in (("rmse_before", "checkpoint (5 x 5)", "o"), ("rmse_control", "control: fine-tuned", "s"),
                          ("rmse_extended", "extended: multi-scale, fine-tuned", "^")):
        ys = [np.nan if r[key] is None else r[key] for r in rows]
        ax.plot(x, ys, marker=mk, label=name)
    ax.set_xticks(x, labels)
    ax.set_xlabel("|CoC| bin (px)")
    ax.set_ylabel("masked RMSE (L and R, held-out)")
    ax.set_title("error vs |CoC|", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[1]
    g = np.array([np.nan if r["gain_db"] is None else r["gain_db"] for r in rows])
    lo = np.array([np.nan if r["gain_ci95"] is None else r["gain_ci95"][0] for r in rows])
    hi = np.array([np.nan if r["gain_ci95"] is None else r["gain_ci95"][1] for r in rows])
    ax.bar(x, np.nan_to_num(g), color="tab:green", alpha=0.7)
    ax.errorbar(x, np.nan_to_num(g), yerr=[np.nan_to_num(g - lo), np.nan_to_num(hi - g)], fmt="none", color="k", capsize=3)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(x, labels)
    ax.set_xlabel("|CoC| bin (px)")
    ax.set_ylabel("PSNR gain, extended - control (dB)")
    ax.set_title("gain per bin, 95 % bootstrap CI over pairs", fontsize=9)
    fig.suptitle(f"Neural DP reach on {res['split']} ({res['n_pairs']} pairs), {res['finetune']['steps']} fine-tune steps",
                 fontsize=10)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return path.name


def diagnose_neural(dataset: str | Path, checkpoint: str | Path, out_dir: str | Path, *, steps: int = 150,
                    seed: int = 0, device: str = "cpu", levels: int = 3, lr: float = 5e-5, crop_px: int = 96,
                    batch_size: int = 4, new_lr_mult: float = 100.0, bins: Sequence[float] = BINS_PX,
                    n_boot: int = 2000) -> dict[str, Any]:
    """Diagnose a Neural DP checkpoint's reach, extend it with multi-scale kernels and measure the gain.

    Args:
        dataset: a format-v1 dataset (train split for fine-tuning; test, else val, held out).
        checkpoint: a Neural DP checkpoint written by ``dp5k train`` (single-scale).
        out_dir: where ``neural_reach.json``, ``neural_reach.png``, ``control.pt`` and ``extended.pt`` go.
        steps: fine-tuning steps, the same for the control and the extension.
        seed: crops, data order, dropout and bootstrap seed.
        device: "cpu", "cuda", "cuda:N" or "auto".
        levels: extra kernel scales (dilations 2, ..., 2**levels px).
        lr: peak fine-tuning learning rate of the checkpoint's own weights (cosine to 0). Low (5e-5), so
            that fine-tuning does not undo a well-trained checkpoint: at 5e-4 the control lost 0.8-1.0 dB
            in 150 steps (docs/diagnose.md, Limits).
        crop_px: fine-tuning crop side in px.
        batch_size: fine-tuning crops per step.
        new_lr_mult: learning-rate factor of the added multi-scale head (see :func:`finetune`); 100, i.e.
            the new, zero-initialised blend weights learn at 5e-3.
        bins: |CoC| bin edges in px.
        n_boot: bootstrap resamples.

    Returns:
        A JSON-able dict (also written to ``out_dir/neural_reach.json``) with keys ``model``, ``dataset``,
        ``checkpoint``, ``split``, ``n_pairs``, ``extension`` (kind, levels, dilations, reach before/after
        in px, extra parameters, ``init_max_abs_diff``: max |extended - checkpoint| on the held-out views
        before fine-tuning, 0 by construction), ``finetune`` (steps, lr, crop, batch, seed, per-step losses
        and seconds of both runs), ``metrics`` (``before`` / ``control`` / ``extended``: mean masked PSNR,
        SSIM, MAE over pairs), ``gain`` (issue-7 shape: checkpoint before, extended after, PSNR gain CI),
        ``gain_vs_control`` (same shape, control before), ``bins_px``, ``per_bin`` (per |CoC| bin: pixels,
        pairs, pooled RMSE / MAE, unexplained fraction and mean per-pair PSNR of the three models, ``gain_db`` and ``gain_ci95`` of
        extended over control, ``gain_vs_before_db``), ``error_growth`` (of the checkpoint: pooled MSE per
        bin, Spearman rho of MSE against bin, ``grows``: rho > 0 and last non-empty bin's MSE above the
        first's; the same for the unexplained fraction, SSE over the no-blur reference's SSE, which
        does not depend on how much texture a bin happens to hold), ``figures`` and ``checkpoints``. NaN values are written as null.

    Raises:
        BadInputError: unreadable checkpoint, a multi-scale checkpoint, or no held-out pairs.
        DatasetFormatError: empty train split.
    """
    t_all = time.perf_counter()
    dev = _resolve_device(device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    reader = DatasetReader(dataset)
    split = "test" if reader.ids("test") else "val"
    held_ids = reader.ids(split)
    if not held_ids:
        raise BadInputError("no test or val pairs to hold out", where=reader.root / "dataset.json")
    held = full_samples(load_pairs(reader, held_ids), str(dev))

    before = NeuralDPSimulator.from_checkpoint(checkpoint, map_location=dev).to(dev)
    if before.cfg.multiscale_levels:
        raise BadInputError("the checkpoint already has multi-scale kernels", where=checkpoint)
    before.eval()

    def predictor(sim: NeuralDPSimulator) -> Predict:
        return lambda s: sim(s.batch)

    # (a) the checkpoint as it is
    err_before = bin_errors(predictor(before), held, bins)
    pm_before = pair_metrics(predictor(before), held)

    # (b) the extension, exactly equal to the checkpoint at init
    ext_net = extend_multiscale(copy.deepcopy(before.net), levels)
    extended = NeuralDPSimulator(ext_net.cfg, ext_net).to(dev).eval()
    with torch.no_grad():
        diff = 0.0
        for s in held:
            l0, r0 = before(s.batch)
            l1, r1 = extended(s.batch)
            diff = max(diff, float((l1 - l0).abs().max()), float((r1 - r0).abs().max()))
    border = ext_net.reach_px  # one loss mask for both runs
    ft = {"lr": lr, "new_lr_mult": new_lr_mult, "crop_px": crop_px, "batch_size": batch_size, "seed": seed,
          "border_px": border}
    t0 = time.perf_counter()
    loss_ext = finetune(extended, dataset, steps, seed=seed, lr=lr, crop_px=crop_px, batch_size=batch_size,
                        border_px=border, new_lr_mult=new_lr_mult, device=dev, desc="fine-tune extended")
    t_ext = time.perf_counter() - t0

    # (c) the control: the unextended checkpoint, same data, budget and mask
    control = NeuralDPSimulator.from_checkpoint(checkpoint, map_location=dev).to(dev)
    t0 = time.perf_counter()
    loss_ctl = finetune(control, dataset, steps, seed=seed, lr=lr, crop_px=crop_px, batch_size=batch_size,
                        border_px=border, device=dev, desc="fine-tune control")
    t_ctl = time.perf_counter() - t0

    # (d) metrics
    err_ctl = bin_errors(predictor(control), held, bins)
    err_ext = bin_errors(predictor(extended), held, bins)
    pm_ctl = pair_metrics(predictor(control), held)
    pm_ext = pair_metrics(predictor(extended), held)

    edges = list(bins)
    per_bin = []
    mse_b, mse_c, mse_e = err_before.pooled_mse(), err_ctl.pooled_mse(), err_ext.pooled_mse()
    mae_b, mae_c, mae_e = err_before.pooled_mae(), err_ctl.pooled_mae(), err_ext.pooled_mae()
    un_b, un_c, un_e = err_before.unexplained(), err_ctl.unexplained(), err_ext.unexplained()
    for j, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        g = err_ext.psnr[:, j] - err_ctl.psnr[:, j]
        gb = err_ext.psnr[:, j] - err_before.psnr[:, j]
        ok = np.isfinite(g)
        per_bin.append({
            "bin_px": [lo, hi if math.isfinite(hi) else None],
            "pixels": int(round(err_before.count[:, j].sum() / 6.0)),
            "n_pairs": int(ok.sum()),
            "rmse_before": math.sqrt(mse_b[j]) if np.isfinite(mse_b[j]) else None,
            "rmse_control": math.sqrt(mse_c[j]) if np.isfinite(mse_c[j]) else None,
            "rmse_extended": math.sqrt(mse_e[j]) if np.isfinite(mse_e[j]) else None,
            "mae_before": mae_b[j], "mae_control": mae_c[j], "mae_extended": mae_e[j],
            "unexplained_before": un_b[j], "unexplained_control": un_c[j], "unexplained_extended": un_e[j],
            "psnr_before": float(np.nanmean(err_before.psnr[:, j])) if ok.any() else None,
            "psnr_control": float(np.nanmean(err_ctl.psnr[:, j])) if ok.any() else None,
            "psnr_extended": float(np.nanmean(err_ext.psnr[:, j])) if ok.any() else None,
            "gain_db": float(g[ok].mean()) if ok.any() else None,
            "gain_ci95": list(bootstrap_ci(g[ok], n_boot, seed=seed)) if ok.any() else None,
            "gain_vs_before_db": float(gb[ok].mean()) if ok.any() else None,
        })
    nonempty = np.flatnonzero(np.isfinite(mse_b))
    rho = _spearman(np.arange(len(mse_b), dtype=float), mse_b)
    grows = bool(nonempty.size >= 2 and rho > 0 and mse_b[nonempty[-1]] > mse_b[nonempty[0]])
    rho_un = _spearman(np.arange(len(un_b), dtype=float), un_b)

    def means(pm: Any) -> dict[str, float]:
        return {"psnr": float(np.nanmean(pm.psnr)), "ssim": float(np.nanmean(pm.ssim)), "mae": float(np.nanmean(pm.mae))}

    n_extra = sum(p.numel() for n, p in ext_net.named_parameters() if n.startswith("scale_head."))
    paths = {"control": str(out / "control.pt"), "extended": str(out / "extended.pt")}
    for name, sim in (("control", control), ("extended", extended)):
        save_checkpoint(paths[name], {"model": sim.net.state_dict(), "model_config": asdict(sim.cfg),
                                      "source_checkpoint": str(checkpoint), "finetune_steps": int(steps)})
    res: dict[str, Any] = {
        "model": f"neural:{checkpoint}",
        "dataset": str(dataset),
        "checkpoint": str(checkpoint),
        "split": split,
        "n_pairs": len(pm_before.pair_ids),
        "extension": {
            "kind": "multiscale_kernels", "multiscale_levels": int(levels), "dilations_px": list(ext_net.dilations),
            "kernel_size": int(ext_net.cfg.kernel_size), "reach_px_before": int(before.net.reach_px),
            "reach_px_after": int(ext_net.reach_px), "extra_parameters": int(n_extra), "init_max_abs_diff": diff,
        },
        "finetune": {**ft, "steps": int(steps), "loss_control": loss_ctl, "loss_extended": loss_ext,
                     "seconds_control": t_ctl, "seconds_extended": t_ext},
        "metrics": {"before": means(pm_before), "control": means(pm_ctl), "extended": means(pm_ext)},
        "gain": gain_report(pm_before, pm_ext, split, n_boot, seed),
        "gain_vs_control": gain_report(pm_ctl, pm_ext, split, n_boot, seed),
        "bins_px": [[lo, hi if math.isfinite(hi) else None] for lo, hi in zip(edges[:-1], edges[1:])],
        "per_bin": per_bin,
        "error_growth": {"pooled_mse_before": list(mse_b), "spearman_rho": rho, "grows": grows,
                         "unexplained_before": list(un_b), "unexplained_spearman_rho": rho_un},
        "checkpoints": paths,
    }
    res = _nan_to_none(res)
    res["figures"] = [plot_reach(res, out / "neural_reach.png")]
    res["seconds"] = time.perf_counter() - t_all
    write_json_atomic(out / "neural_reach.json", res)
    return res


def format_table(res: dict[str, Any]) -> str:
    """A markdown table of the per-bin result (as in docs/diagnose.md)."""
    def f(x: Any, nd: int = 2) -> str:
        return "-" if x is None else f"{x:.{nd}f}"

    lines = ["| abs(CoC) px | pixels | pairs | PSNR before | control | extended | gain vs control (95 % CI) |",
             "|---|---|---|---|---|---|---|"]
    for r in res["per_bin"]:
        lo, hi = r["bin_px"]
        if r["pixels"] == 0:
            continue
        ci = r["gain_ci95"]
        gain = "-" if r["gain_db"] is None else f"{r['gain_db']:+.2f} [{ci[0]:+.2f}, {ci[1]:+.2f}]"
        lines.append(f"| {_bin_label(lo, math.inf if hi is None else hi)} | {r['pixels']} | {r['n_pairs']} | "
                     f"{f(r['psnr_before'])} | {f(r['psnr_control'])} | {f(r['psnr_extended'])} | {gain} |")
    m = res["metrics"]
    g = res["gain_vs_control"]
    lines.append(f"| all (PSNR / SSIM / MAE) | | {res['n_pairs']} | {m['before']['psnr']:.2f} / {m['before']['ssim']:.4f} / "
                 f"{m['before']['mae']:.4f} | {m['control']['psnr']:.2f} / {m['control']['ssim']:.4f} / {m['control']['mae']:.4f} | "
                 f"{m['extended']['psnr']:.2f} / {m['extended']['ssim']:.4f} / {m['extended']['mae']:.4f} | "
                 f"{g['psnr_after'] - g['psnr_before']:+.2f} [{g['psnr_gain_ci95'][0]:+.2f}, {g['psnr_gain_ci95'][1]:+.2f}] |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("checkpoint")
    ap.add_argument("out")
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--lr", type=float, default=5e-5)
    ap.add_argument("--new-lr-mult", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    res = diagnose_neural(a.dataset, a.checkpoint, a.out, steps=a.steps, seed=a.seed, device=a.device,
                          levels=a.levels, lr=a.lr, new_lr_mult=a.new_lr_mult)
    print(format_table(res))
    print(json.dumps({k: res[k] for k in ("extension", "metrics", "error_growth")}, indent=1))


if __name__ == "__main__":
    main()
