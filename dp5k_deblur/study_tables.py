"""The downstream study's tables: every row's mean scores with 95 % intervals over test pairs and seeds, the
differences between rows and which of them are resolved, as JSON, Markdown, sentences and a figure.

A row holds one score array per metric, ``(S, P)`` (seeds x test pairs) or ``(1, P)`` for a setting that does not
depend on a seed (the blurred input). Intervals come from :class:`dp5k_learn.intervals.Resampler` (a two-way
bootstrap over the test set's scenes and the seeds), one per test set, so every row and difference of a test set
is drawn from the same replicates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dp5k_common.io import atomic_path
from dp5k_learn.intervals import Difference, Estimate, Resampler

from .evaluate import METRICS, DeblurScores

FIGURE_MARGIN_DB = 0.3
"""Space above and below the figure's PSNR range, dB."""
INPUT_ROW = "blurred input L + R (no deblurring)"


@dataclass(frozen=True)
class Row:
    """One setting's scores on one test set: ``values[metric]`` is ``(S, P)`` or ``(1, P)``."""

    setting: str
    values: dict[str, NDArray[np.float64]]
    simulator: str | None = None
    """The simulator's label for the rows of synthetic data."""

    @classmethod
    def of(cls, setting: str, per_seed: Sequence[DeblurScores], pair_ids: Sequence[str], key: str = "prediction",
           simulator: str | None = None) -> Row:
        """From one :class:`DeblurScores` per seed (``key``: "prediction" or "input"), columns in ``pair_ids`` order."""
        values = {}
        for m in METRICS:
            grid = [[{p["pair_id"]: p[key][m] for p in s.pairs}[pid] for pid in pair_ids] for s in per_seed]
            values[m] = np.asarray(grid, dtype=np.float64)
        return cls(setting, values, simulator)


def row_json(row: Row, floor: Row, rs: Resampler) -> dict[str, Any]:
    """Means and intervals of every metric, the PSNR gain over the blurred input, and the per-seed means."""
    out: dict[str, Any] = {"setting": row.setting}
    if row.simulator:
        out["simulator"] = row.simulator
    for m in METRICS:
        e = rs.estimate(row.values[m])
        out[m], out[f"{m}_ci95"] = e.mean, [e.lo, e.hi]
    if row is not floor:
        out["psnr_gain_vs_input"] = rs.difference(row.values["psnr"], floor.values["psnr"]).to_json()
    out["per_seed"] = {m: [float(np.nanmean(v)) for v in row.values[m]] for m in METRICS}
    return out


def differences(t3: Sequence[Row], t4: Sequence[Row], rs: Resampler) -> list[Difference]:
    """The comparisons the study reports (PSNR, ``a - b`` with ``a`` the higher mean):

    * Table 3: every trained row against the blurred input, and every two simulators' rows;
    * Table 4: every row against the few measured pairs alone, every two fine-tuned simulators' rows, and the
      deblurrer of all measured train pairs against the best synthetic row of either table.
    """
    floor, synth3 = t3[0], [r for r in t3 if r.simulator]
    few, all_measured, synth4 = t4[0], t4[1], [r for r in t4 if r.simulator]

    def diff(a: Row, b: Row) -> Difference:
        return rs.compare(a.setting, a.values["psnr"], b.setting, b.values["psnr"])

    out = [diff(r, floor) for r in t3[1:]]
    out += [diff(a, b) for a, b in combinations(synth3, 2)]
    out += [diff(r, few) for r in t4[1:]]
    out += [diff(a, b) for a, b in combinations(synth4, 2)]
    synth = synth3 + synth4
    if synth:
        best = max(synth, key=lambda r: float(np.nanmean(r.values["psnr"])))
        out.append(diff(all_measured, best))
    return out


def _ci(value: float, ci: Sequence[float], digits: int, signed: bool = False) -> str:
    return Estimate(value, ci[0], ci[1]).text(digits, signed)


def markdown(title: str, rows: Sequence[dict[str, Any]], note: str) -> str:
    """A table of :func:`row_json` rows: PSNR, its gain over L + R, SSIM and MAE, each with its 95 % interval."""
    lines = [f"### {title}", "", note, "",
             "| setting | PSNR (dB) [95 % CI] | vs L + R (dB) [95 % CI] | SSIM [95 % CI] | MAE [95 % CI] |",
             "|---|---|---|---|---|"]
    for r in rows:
        gain = r.get("psnr_gain_vs_input")
        g = _ci(gain["mean"], gain["ci95"], 2, signed=True) if gain else ""
        lines.append(f"| {r['setting']} | {_ci(r['psnr'], r['psnr_ci95'], 2)} | {g} | {_ci(r['ssim'], r['ssim_ci95'], 4)} | "
                     f"{_ci(r['mae'], r['mae_ci95'], 4)} |")
    return "\n".join(lines) + "\n"


def figure(path: Path, t3: Sequence[dict[str, Any]], t4: Sequence[dict[str, Any]], title: str) -> None:
    """Bars with 95 % whiskers: test PSNR per simulator, synthetic only and fine-tuned; lines: L + R and the
    deblurrer of all measured train pairs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sims = [r for r in t3 if r.get("simulator")]
    tuned = {r["simulator"]: r for r in t4 if r.get("simulator")}
    fig, ax = plt.subplots(figsize=(1.2 * len(sims) + 3, 3.4))
    xs = np.arange(len(sims))
    for dx, rows, label in ((-0.2, sims, "synthetic only (Table 3)"),
                            (0.2, [tuned.get(r["simulator"]) for r in sims], "+ fine-tune (Table 4)")):
        ok = [r for r in rows if r is not None]
        x = [xi + dx for xi, r in zip(xs, rows) if r is not None]
        mean = np.array([r["psnr"] for r in ok])
        err = np.array([[m - r["psnr_ci95"][0], r["psnr_ci95"][1] - m] for m, r in zip(mean, ok)]).T.reshape(2, -1)
        ax.bar(x, mean, 0.4, yerr=err, capsize=3, label=label)
    for r, color, style in ((t3[0], "k", "--"), (t4[1], "g", ":")):
        ax.axhline(r["psnr"], color=color, linestyle=style, label=r["setting"])
        ax.axhspan(*r["psnr_ci95"], color=color, alpha=0.08)
    ax.set_xticks(list(xs), [r["simulator"] for r in sims])
    ax.set_ylabel("test PSNR vs sharp (dB)")
    ax.set_title(title, fontsize=9)
    values = [v for r in [*t3, *t4] for v in r["psnr_ci95"]]
    ax.set_ylim(min(values) - FIGURE_MARGIN_DB, max(values) + FIGURE_MARGIN_DB)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
