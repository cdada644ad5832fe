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
   fixed number of steps (extended; :func:`neural_dp.train.finetune`, the training loop's own step);
3. fine-tunes the unextended checkpoint with the same data, order, optimiser, loss mask and budget
   (control), so the gain is the structure's, not the extra training's;
4. reports masked PSNR / SSIM / MAE (``dp5k_learn.metrics``) before / control / extended, per-|CoC|-bin PSNR of
   all three, the per-bin PSNR gain of extended over control with a bootstrap CI over pairs
   (:func:`dp5k_diagnose.gain.bootstrap_ci`), and writes ``neural_reach.png`` (error vs |CoC|, gain per bin),
   ``neural_reach.json`` and the two fine-tuned checkpoints (``control.pt``, ``extended.pt``; both load with
   ``get_simulator("neural", checkpoint=...)``).

Run it with ``dp5k diagnose DATASET --simulator neural:CKPT`` (``--neural-steps``); settings: :class:`NeuralReachConfig`.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dp5k_common.dataset import DatasetReader
from dp5k_common.errors import BadInputError
from dp5k_common.io import atomic_path, write_json_atomic
from dp5k_learn.checkpoint import save_checkpoint
from dp5k_learn.config import FinetuneConfig
from neural_dp.registry import NEW_PARAMETER_PREFIX, NeuralDPSimulator, extend_multiscale, finetune

from .data import Sample, full_samples, load_pairs
from .gain import PairMetrics, bootstrap_ci, gain_report, pair_metrics

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


@dataclass(frozen=True)
class NeuralReachConfig:
    """Settings of :func:`diagnose_neural`.

    Attributes:
        finetune: how the extension and the control are fine-tuned (the same for both); its seed also seeds
            the bootstrap.
        levels: extra kernel scales of the extension (dilations 2, ..., 2**levels px).
        bins_px: increasing |CoC| bin edges in px (the last bin is open).
        n_boot: bootstrap resamples of the per-bin CIs.
        device: "cpu", "cuda", "cuda:N" or "auto".
    """

    finetune: FinetuneConfig = field(default_factory=FinetuneConfig)
    levels: int = 3
    bins_px: tuple[float, ...] = BINS_PX
    n_boot: int = 2000
    device: str = "cpu"


@dataclass
class _Arm:
    """One simulator of the study on the held-out samples: its errors per |CoC| bin and its metrics per pair."""

    sim: NeuralDPSimulator
    bins: BinErrors
    metrics: PairMetrics


def _measure(sim: NeuralDPSimulator, held: Sequence[Sample], bins: Sequence[float]) -> _Arm:
    def predict(s: Sample) -> tuple[Tensor, Tensor]:
        return sim(s.batch)

    return _Arm(sim, bin_errors(predict, held, bins), pair_metrics(predict, held))


def held_out_samples(reader: DatasetReader, device: torch.device) -> tuple[str, list[Sample]]:
    """The held-out split (test, else val) as whole pairs: (split name, samples).

    Raises:
        BadInputError: neither split has a pair.
    """
    split = "test" if reader.ids("test") else "val"
    ids = reader.ids(split)
    if not ids:
        raise BadInputError("no test or val pairs to hold out", where=reader.root / "dataset.json")
    return split, full_samples(load_pairs(reader, ids), str(device))


def load_single_scale(checkpoint: str | Path, device: torch.device) -> NeuralDPSimulator:
    """The checkpoint's simulator in eval mode.

    Raises:
        BadInputError: the checkpoint already has multi-scale kernels (there is nothing to extend).
    """
    sim = NeuralDPSimulator.from_checkpoint(checkpoint, map_location=device).to(device)
    if sim.cfg.multiscale_levels:
        raise BadInputError("the checkpoint already has multi-scale kernels", where=checkpoint)
    return sim.eval()


def extend_exactly(before: NeuralDPSimulator, levels: int, held: Sequence[Sample], device: torch.device) -> tuple[NeuralDPSimulator, float]:
    """The checkpoint with multi-scale kernels added (:func:`neural_dp.model.extend_multiscale`, zero blend
    weights), and the largest |difference| of its views from the checkpoint's on the held-out samples (0 by
    construction; reported, so that a gain is never an artefact of the initialisation)."""
    net = extend_multiscale(copy.deepcopy(before.net), levels)
    extended = NeuralDPSimulator(net.cfg, net).to(device).eval()
    diff = 0.0
    with torch.no_grad():
        for s in held:
            l0, r0 = before(s.batch)
            l1, r1 = extended(s.batch)
            diff = max(diff, float((l1 - l0).abs().max()), float((r1 - r0).abs().max()))
    return extended, diff


def _timed_finetune(sim: NeuralDPSimulator, dataset: str | Path, cfg: FinetuneConfig, device: torch.device,
                    desc: str) -> tuple[list[float], float]:
    t0 = time.perf_counter()
    losses = finetune(sim, dataset, cfg, device, desc)
    return losses, time.perf_counter() - t0


def per_bin_table(before: BinErrors, control: BinErrors, extended: BinErrors, bins: Sequence[float], n_boot: int,
                  seed: int) -> list[dict[str, Any]]:
    """Per |CoC| bin: pixels, pairs, pooled RMSE / MAE and unexplained fraction and mean per-pair PSNR of the
    three simulators, and the PSNR gain of extended over control (with its bootstrap CI over pairs) and over
    the checkpoint. Non-finite values stay NaN (written as null)."""
    edges = list(bins)
    mse = [a.pooled_mse() for a in (before, control, extended)]
    mae = [a.pooled_mae() for a in (before, control, extended)]
    un = [a.unexplained() for a in (before, control, extended)]
    rows = []
    for j, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        g = extended.psnr[:, j] - control.psnr[:, j]
        gb = extended.psnr[:, j] - before.psnr[:, j]
        ok = np.isfinite(g)
        rmse = [math.sqrt(m[j]) if np.isfinite(m[j]) else None for m in mse]
        psnr = [float(np.nanmean(a.psnr[:, j])) if ok.any() else None for a in (before, control, extended)]
        rows.append({
            "bin_px": [lo, hi if math.isfinite(hi) else None],
            "pixels": int(round(before.count[:, j].sum() / 6.0)),
            "n_pairs": int(ok.sum()),
            "rmse_before": rmse[0], "rmse_control": rmse[1], "rmse_extended": rmse[2],
            "mae_before": mae[0][j], "mae_control": mae[1][j], "mae_extended": mae[2][j],
            "unexplained_before": un[0][j], "unexplained_control": un[1][j], "unexplained_extended": un[2][j],
            "psnr_before": psnr[0], "psnr_control": psnr[1], "psnr_extended": psnr[2],
            "gain_db": float(g[ok].mean()) if ok.any() else None,
            "gain_ci95": list(bootstrap_ci(g[ok], n_boot, seed=seed)) if ok.any() else None,
            "gain_vs_before_db": float(gb[ok].mean()) if ok.any() else None,
        })
    return rows


def error_growth(before: BinErrors) -> dict[str, Any]:
    """How the checkpoint's error grows with |CoC|: pooled MSE per bin and its Spearman rho against the bin,
    ``grows`` (rho > 0 and the last non-empty bin's MSE above the first's), and the same rho for the
    unexplained fraction (SSE over the no-blur reference's SSE, independent of how much texture a bin holds)."""
    mse, un = before.pooled_mse(), before.unexplained()
    nonempty = np.flatnonzero(np.isfinite(mse))
    rho = _spearman(np.arange(len(mse), dtype=float), mse)
    grows = bool(nonempty.size >= 2 and rho > 0 and mse[nonempty[-1]] > mse[nonempty[0]])
    return {"pooled_mse_before": list(mse), "spearman_rho": rho, "grows": grows,
            "unexplained_before": list(un), "unexplained_spearman_rho": _spearman(np.arange(len(un), dtype=float), un)}


def save_finetuned(out: Path, arms: dict[str, NeuralDPSimulator], checkpoint: str | Path, steps: int) -> dict[str, str]:
    """``out/<name>.pt`` for each fine-tuned simulator (loadable with ``get_simulator("neural", checkpoint=...)``)."""
    paths = {name: str(out / f"{name}.pt") for name in arms}
    for name, sim in arms.items():
        save_checkpoint(paths[name], {"model": sim.net.state_dict(), "model_config": asdict(sim.cfg),
                                      "source_checkpoint": str(checkpoint), "finetune_steps": int(steps)})
    return paths


def _means(pm: PairMetrics) -> dict[str, float]:
    return {"psnr": float(np.nanmean(pm.psnr)), "ssim": float(np.nanmean(pm.ssim)), "mae": float(np.nanmean(pm.mae))}


def diagnose_neural(dataset: str | Path, checkpoint: str | Path, out_dir: str | Path,
                    cfg: NeuralReachConfig = NeuralReachConfig()) -> dict[str, Any]:
    """Diagnose a Neural DP checkpoint's reach, extend it with multi-scale kernels and measure the gain.

    Steps: the held-out samples (:func:`held_out_samples`); the checkpoint's errors per |CoC| bin; the exact
    extension (:func:`extend_exactly`); the extension and the unextended control fine-tuned with the same
    settings and loss mask (:func:`neural_dp.train.finetune`); their errors; the per-bin table
    (:func:`per_bin_table`), the checkpoint's :func:`error_growth`, the fine-tuned checkpoints
    (:func:`save_finetuned`), the figure and ``neural_reach.json``.

    Args:
        dataset: a format-v1 dataset (train split for fine-tuning; test, else val, held out).
        checkpoint: a Neural DP checkpoint written by ``dp5k train`` (single-scale).
        out_dir: where ``neural_reach.json``, ``neural_reach.png``, ``control.pt`` and ``extended.pt`` go.
        cfg: the study's settings (:class:`NeuralReachConfig`).

    Returns:
        A JSON-able dict (also written to ``out_dir/neural_reach.json``) with keys ``model``, ``dataset``,
        ``checkpoint``, ``split``, ``n_pairs``, ``extension`` (kind, levels, dilations, reach before/after
        in px, extra parameters, ``init_max_abs_diff``: max |extended - checkpoint| on the held-out views
        before fine-tuning, 0 by construction), ``finetune`` (steps, lr, crop, batch, seed, per-step losses
        and seconds of both runs), ``metrics`` (``before`` / ``control`` / ``extended``: mean masked PSNR,
        SSIM, MAE over pairs), ``gain`` (issue-7 shape: checkpoint before, extended after, PSNR gain CI),
        ``gain_vs_control`` (same shape, control before), ``bins_px``, ``per_bin`` (:func:`per_bin_table`),
        ``error_growth`` (:func:`error_growth`), ``figures`` and ``checkpoints``. NaN values are written as null.

    Raises:
        BadInputError: unreadable checkpoint, a multi-scale checkpoint, or no held-out pairs.
        EmptySplitError: empty train split.
    """
    t_all = time.perf_counter()
    dev = _resolve_device(cfg.device)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    split, held = held_out_samples(DatasetReader(dataset), dev)
    bins, ft = cfg.bins_px, cfg.finetune

    before = _measure(load_single_scale(checkpoint, dev), held, bins)
    extended_sim, init_diff = extend_exactly(before.sim, cfg.levels, held, dev)
    ft = replace(ft, border_px=extended_sim.net.reach_px if ft.border_px is None else ft.border_px)  # one loss mask for both
    loss_ext, t_ext = _timed_finetune(extended_sim, dataset, ft, dev, "fine-tune extended")
    control_sim = load_single_scale(checkpoint, dev)
    loss_ctl, t_ctl = _timed_finetune(control_sim, dataset, ft, dev, "fine-tune control")
    control, extended = _measure(control_sim, held, bins), _measure(extended_sim, held, bins)

    net = extended_sim.net
    res: dict[str, Any] = {
        "model": f"neural:{checkpoint}",
        "dataset": str(dataset),
        "checkpoint": str(checkpoint),
        "split": split,
        "n_pairs": len(before.metrics.pair_ids),
        "extension": {
            "kind": "multiscale_kernels", "multiscale_levels": int(cfg.levels), "dilations_px": list(net.dilations),
            "kernel_size": int(net.cfg.kernel_size), "reach_px_before": int(before.sim.net.reach_px),
            "reach_px_after": int(net.reach_px), "init_max_abs_diff": init_diff,
            "extra_parameters": int(sum(p.numel() for n, p in net.named_parameters() if n.startswith(NEW_PARAMETER_PREFIX))),
        },
        "finetune": {"lr": ft.lr, "new_lr_mult": ft.new_lr_mult, "crop_px": ft.crop_px, "batch_size": ft.batch_size,
                     "seed": ft.seed, "border_px": ft.border_px, "steps": int(ft.steps), "loss_control": loss_ctl,
                     "loss_extended": loss_ext, "seconds_control": t_ctl, "seconds_extended": t_ext},
        "metrics": {"before": _means(before.metrics), "control": _means(control.metrics), "extended": _means(extended.metrics)},
        "gain": gain_report(before.metrics, extended.metrics, split, cfg.n_boot, ft.seed),
        "gain_vs_control": gain_report(control.metrics, extended.metrics, split, cfg.n_boot, ft.seed),
        "bins_px": [[lo, hi if math.isfinite(hi) else None] for lo, hi in zip(bins[:-1], bins[1:])],
        "per_bin": per_bin_table(before.bins, control.bins, extended.bins, bins, cfg.n_boot, ft.seed),
        "error_growth": error_growth(before.bins),
        "checkpoints": save_finetuned(out, {"control": control_sim, "extended": extended_sim}, checkpoint, ft.steps),
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
