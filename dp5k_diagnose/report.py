"""Write a diagnosis: ``report.json``, ``report.md`` with its figures, and ``atlas.npz`` (every file atomically)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from dp5k_common.io import atomic_path, write_json_atomic  # noqa: E402
from dp5k_common.software import software_line  # noqa: E402

from .atlas import COARSE, FINE, ZONES, Atlas, save_atlas  # noqa: E402

VIEW_SET_LABEL = {"measured": "measured", "simulator": "simulator", "extended": "extended model", "peer": "peer"}


def _save(fig: Any, path: Path) -> str:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, bbox_inches="tight", format="png")
    plt.close(fig)
    return path.name


def _kernel_image(k: np.ndarray) -> np.ndarray:
    """(3, K, K) -> (K, K) the channels' mean."""
    return k.mean(0)


def plot_atlas_by_coc(atlas: Atlas, path: Path, max_bins: int = 12) -> str:
    """The whole field's kernels by CoC bin (columns), L and R of each view-set (rows), one colour scale per column."""
    bins = atlas.measured_bins(-1)
    if len(bins) > max_bins:
        bins = [bins[i] for i in np.linspace(0, len(bins) - 1, max_bins).round().astype(int)]
    names = [n for n in ("measured", "simulator", "extended", "peer") if n in atlas.names]
    rows = [(n, v) for n in names for v in (0, 1)]
    fig, axes = plt.subplots(len(rows), max(len(bins), 1), figsize=(1.25 * max(len(bins), 1), 1.3 * len(rows)), squeeze=False)
    for j, b in enumerate(bins):
        ks = {n: atlas.kernels((b, -1), n) for n in names}
        vmax = max(float(np.abs(_kernel_image(ks[n][v])).max()) for n, v in rows) or 1.0
        for i, (n, v) in enumerate(rows):
            ax = axes[i, j]
            ax.imshow(_kernel_image(ks[n][v]), cmap="RdBu_r", vmin=-vmax, vmax=vmax)
            ax.set_xticks([]); ax.set_yticks([])
            if i == 0:
                ax.set_title(f"CoC {atlas.cells[(b, -1)].mean_coc_px:+.1f}", fontsize=7)
            if j == 0:
                ax.set_ylabel(f"{VIEW_SET_LABEL.get(n, n)} {'LR'[v]}", fontsize=7)
    fig.suptitle("PSF atlas, whole field: each view's kernel from sharp, by signed CoC (px); red = light, blue = negative", fontsize=8)
    return _save(fig, path)


def plot_atlas_by_zone(atlas: Atlas, path: Path) -> str | None:
    """Each field zone's kernels (3 x 3 grid per panel) at the most populated zone bin behind and in front of focus,
    measured and simulator, L and R."""
    zone_bins: dict[int, float] = {}
    for (b, z), c in atlas.cells.items():
        if z >= 0 and c.measured and b != 0:
            zone_bins[b] = zone_bins.get(b, 0.0) + float(c.pixels.sum())
    picks = [b for b in (max((b for b in zone_bins if b > 0), key=zone_bins.get, default=None),
                         max((b for b in zone_bins if b < 0), key=zone_bins.get, default=None)) if b is not None]
    names = [n for n in ("measured", "simulator") if n in atlas.names]
    if not picks or not names:
        return None
    panels = [(b, n, v) for b in picks for n in names for v in (0, 1)]
    fig, axes = plt.subplots(ZONES, ZONES * len(panels), figsize=(0.9 * ZONES * len(panels), 0.95 * ZONES), squeeze=False)
    for p, (b, n, v) in enumerate(panels):
        keys = [(b, z) for z in range(ZONES * ZONES) if (b, z) in atlas.cells and atlas.cells[(b, z)].measured]
        vmax = max((float(np.abs(_kernel_image(atlas.kernels(k, n)[v])).max()) for k in keys), default=1.0) or 1.0
        for z in range(ZONES * ZONES):
            zy, zx = divmod(z, ZONES)
            ax = axes[zy, p * ZONES + zx]
            ax.set_xticks([]); ax.set_yticks([])
            if (b, z) in keys:
                ax.imshow(_kernel_image(atlas.kernels((b, z), n)[v]), cmap="RdBu_r", vmin=-vmax, vmax=vmax)
            else:
                ax.set_facecolor("0.85")
            if zy == 0 and zx == 1:
                lo, hi = COARSE.edges(b)
                ax.set_title(f"{VIEW_SET_LABEL.get(n, n)} {'LR'[v]}, CoC {lo:g}..{hi:g}", fontsize=7)
    fig.suptitle("PSF atlas by field zone (3 x 3 over the frame; grey: not measured)", fontsize=8)
    return _save(fig, path)


def plot_signatures(sigs: dict[str, dict[str, Any]], named: set[str], path: Path) -> str:
    """Each effect's strongest value over its minimum, with its interval; red where the effect was named."""
    rows = []
    for e, s in sigs.items():
        vals = [v for v in s["values"] if v["value"] is not None and v["min_effect"]]
        if not vals:
            rows.append((e, 0.0, 0.0, 0.0, s.get("unmeasured") or "not measured"))
            continue
        v = max(vals, key=lambda v: abs(v["value"]) / v["min_effect"])
        lo, hi = (x if x is not None else np.nan for x in v["interval95"])
        rows.append((e, abs(v["value"]) / v["min_effect"], abs(lo) / v["min_effect"] if np.isfinite(lo) else 0.0,
                     abs(hi) / v["min_effect"] if np.isfinite(hi) else 0.0, v["name"]))
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(rows) + 1))
    ys = np.arange(len(rows))[::-1]
    for y, (e, val, lo, hi, what) in zip(ys, rows):
        ax.barh(y, val, color="tab:red" if e in named else "tab:gray")
        ax.plot([min(lo, hi), max(lo, hi)], [y, y], color="k", lw=1)
        ax.text(max(val, hi) + 0.05, y, what, fontsize=6, va="center")
    ax.axvline(1.0, color="k", ls="--", lw=0.8)
    ax.set_yticks(ys, [r[0] for r in rows], fontsize=7)
    ax.set_xlabel("|measured - simulator| over the effect's minimum (its strongest value; bar: 95 % interval)", fontsize=7)
    return _save(fig, path)


def plot_residuals(tables: dict[str, Any], path: Path, title: str) -> str:
    names = [k for k in tables if k != "channel"]
    fig, axes = plt.subplots(2, (len(names) + 2) // 2, figsize=(16, 6.5))
    for ax, name in zip(axes.flat, names + ["channel"]):
        t = tables[name]
        xs = np.arange(3) if name == "channel" else np.asarray(t["bin_center"], float)
        for col in ("L", "R", "L+R", "L-R"):
            if col in t and len(t[col]):
                ax.plot(xs, t[col], marker="o", ms=3, label=col)
        if name == "channel":
            ax.set_xticks(xs, t["bin_center"])
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(names) + 1 :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(title + ": mean |prediction - measurement| per bin", fontsize=10)
    return _save(fig, path)


def _where(zone: int) -> str:
    return "whole field" if zone < 0 else f"zone {zone}"


def _num(v: Any) -> str:
    return "-" if v is None else f"{v:.4g}"


def signature_lines(result: dict[str, Any]) -> list[str]:
    """report.md's table of every effect's signature against the simulator (before any cause was added)."""
    named = {c["name"] for c in result.get("causes") or []}
    suspects = {s["name"] for s in result.get("suspects") or []}
    explained = {g["names"][1]: g["names"][0] for g in result.get("lookalikes") or []}
    lines = ["## Signatures: the measured atlas against the simulator's", "",
             "Each effect changes its own summary of the kernels (docs/diagnose.md, \"Signatures\"); the table gives it "
             "measured on the data's kernels and on the simulator's renders of the same pairs (with the views' measured "
             "noise), their difference with its 95 % interval (bootstrap over pairs) and the smallest difference that "
             "counts. An effect differs when a value is significant (Bonferroni over the effect's values) and at least its "
             "minimum; it is then tried as a cause.", "",
             "| effect | value | measured | simulator | difference [95 %] | p | minimum | decision |", "|---|---|---|---|---|---|---|---|"]
    for e, s in (result.get("signatures") or {}).items():
        decision = ("named" if e in named else f"explained by `{explained[e]}`" if e in explained else "suspect" if e in suspects
                    else "differs" if s["differs"] else "no difference")
        if s.get("unmeasured"):
            lines.append(f"| `{e}` | - | - | - | - | - | - | not measured: {s['unmeasured']} |")
            continue
        for i, v in enumerate(s["values"]):
            lo, hi = v["interval95"]
            lines.append(f"| {'`' + e + '`' if i == 0 else ''} | {v['name']} ({v['unit']}) | {_num(v['measured'])} | {_num(v['simulator'])} | "
                         f"{_num(v['value'])} [{_num(lo)}, {_num(hi)}] | {_num(v['p_value'])} | {v['min_effect']:g} | {decision if i == 0 else ''} |")
    return lines + [""]


def cause_lines(result: dict[str, Any]) -> list[str]:
    """report.md's causes in order, each in a sentence, with its gains and parameters."""
    causes = result.get("causes") or []
    lines = ["## Causes, in order", ""]
    if not causes:
        return lines + ["No effect's signature differs beyond its interval and its minimum and gains on the held-out pairs: `none`.", ""]
    lines += ["Each cause's signature differed from the simulator's, and the model extended by it predicted the held-out pairs "
              "better (PSNR gain, 95 % interval over 32 px tiles resampled within each pair). *Given the others*: the final "
              "model against it without the cause, refitted; *step*: over the model of the causes before it. `noise` is "
              "measured, not fitted (a prediction is an expectation): its gains are 0.", ""]
    for c in causes:
        sig = c.get("signature") or {}
        v = max(sig.get("values") or [{}], key=lambda v: abs(v.get("value") or 0) / (v.get("min_effect") or 1), default={})
        why = (f" Its signature: {v['name']} {_num(v['value'])} {v['unit']} beyond the simulator's (95 % "
               f"[{_num(v['interval95'][0])}, {_num(v['interval95'][1])}], minimum {v['min_effect']:g})." if v.get("name") else "")
        lo, hi = c["gain_ci_db"]
        iv = c.get("param_intervals", {})
        par = ", ".join(f"{k} {_num(x)}" + (f" [{_num(iv[k][0])}, {_num(iv[k][1])}]" if k in iv else "")
                        for k, x in c["params"].items() if isinstance(x, float))
        lines += [f"{c['step']}. **`{c['name']}`**: {c['explanation']}.{why} Held-out gain given the others {c['gain_db']:+.3f} dB "
                  f"[{lo:+.3f}, {hi:+.3f}], step {c['step_gain_db']:+.3f} dB, cumulative {c['cumulative_gain_db']:+.3f} dB. "
                  f"Parameters: {par}.", ""]
    return lines


def lookalike_lines(result: dict[str, Any]) -> list[str]:
    lines = []
    for g in result.get("lookalikes") or []:
        lines += [f"**`{g['names'][1]}` explained by `{g['names'][0]}`.** {g['why']}. To tell them apart, capture {g['captures'][0]}.", ""]
    for s in result.get("suspects") or []:
        lines += [f"**Suspect, not named: `{s['name']}`.** {s['why']}.", ""]
    return lines


def write_report(out: Path, result: dict[str, Any], analysis: dict[str, Any], atlas: Atlas) -> None:
    """``out/report.json`` (the result, the analysis tables and the figures' names), ``out/report.md`` with figures, and
    ``out/atlas.npz``."""
    out.mkdir(parents=True, exist_ok=True)
    save_atlas(out / "atlas.npz", atlas)
    figs: dict[str, str] = {"atlas_by_coc": plot_atlas_by_coc(atlas, out / "atlas_by_coc.png")}
    z = plot_atlas_by_zone(atlas, out / "atlas_by_zone.png")
    if z:
        figs["atlas_by_zone"] = z
    named = {c["name"] for c in result.get("causes") or []}
    figs["signatures"] = plot_signatures(result.get("signatures") or {}, named, out / "signatures.png")
    for stage in ("before", "after"):
        if analysis.get(stage):
            figs[f"residuals_{stage}"] = plot_residuals(analysis[stage]["residuals"], out / f"residuals_{stage}.png", stage)
    full = {**result, "analysis": analysis, "figures": figs}
    write_json_atomic(out / "report.json", full)
    g = result["gain"]
    causes = result.get("causes") or []
    chain = " -> ".join("`" + c["name"] + "`" for c in causes)
    head = (f"**Causes, in order: {chain}**" if causes
            else "**Cause: `none`**: no effect's signature differs from the simulator's and gains on the held-out pairs.")
    cov = result.get("fit_coverage") or {}
    at = result.get("atlas") or {}
    lines = [f"# dp5k diagnose: `{result['model']}` on `{result['dataset']}`", "", head, "",
             f"The atlas was measured on {at.get('pairs', '?')} pairs ({at.get('measured', '?')} of {at.get('cells', '?')} cells measured; "
             f"`atlas.npz`); the models were fitted on {cov.get('crops', '?')} crops of {cov.get('pairs', '?')} train pairs; gains are "
             f"on the held-out `{g['split']}` split ({g.get('n_pairs', '?')} pairs).", "",
             f"Base model fitted on train: {json.dumps({k: round(v, 4) for k, v in result.get('base_params', {}).items()})}", "",
             *cause_lines(result), *lookalike_lines(result), *signature_lines(result),
             f"![signatures]({figs['signatures']})", "", "## The PSF atlas", "",
             "Kernels measured from the sharp image to each view by regularised least squares over every pair "
             "(docs/diagnose.md, \"The atlas\"), beside the simulator's, measured the same way on its renders of the same pairs.", "",
             f"![atlas by CoC]({figs['atlas_by_coc']})", ""]
    if "atlas_by_zone" in figs:
        lines += [f"![atlas by zone]({figs['atlas_by_zone']})", ""]
    unmeasured = at.get("unmeasured") or []
    if unmeasured:
        lines += [f"{len(unmeasured)} cells are not measured (nothing is named from them): " + "; ".join(
            f"CoC {u['coc_px'][0]:g}..{u['coc_px'][1]:g} {_where(u['zone'])}: {u['why']}"
            for u in unmeasured[:8]) + (" ..." if len(unmeasured) > 8 else "") + ".", ""]
    av = g.get("all_valid", {})
    lines += [f"## Gain on the held-out `{g['split']}` split ({g.get('n_pairs', '?')} pairs)", "",
              "| metric | before | after | before (all valid) | after (all valid) |", "|---|---|---|---|---|"]
    for label, key, fmt in (("masked PSNR (dB)", "psnr", ".3f"), ("masked SSIM", "ssim", ".4f"), ("masked MAE", "mae", ".5f")):
        cells = [format(d[f"{key}_{w}"], fmt) if f"{key}_{w}" in d else "-" for d in (g, av) for w in ("before", "after")]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", f"PSNR gain {g['psnr_after'] - g['psnr_before']:+.3f} dB, 95 % bootstrap CI over pairs "
              f"[{g['psnr_gain_ci95'][0]:+.3f}, {g['psnr_gain_ci95'][1]:+.3f}].", ""]
    for stage in ("before", "after"):
        if f"residuals_{stage}" in figs:
            lines += [f"![residuals {stage}]({figs[f'residuals_{stage}']})", ""]
    nm = result.get("noise_model") or {}
    if nm.get("measured"):
        lines += [f"Measured view noise: variance = shot_var I + read_sigma^2 with shot_var {_num(nm['shot_var'])}, read_sigma "
                  f"{_num(nm['read_sigma'])} (linear units), {nm['variance_ratio']:.2f} x the nominal sensor's.", ""]
    ne = result.get("neural_extension")
    if ne:
        from .neural_reach import format_table

        gc = ne["gain_vs_control"]
        lines += ["## The learned model's reach and its structural extension", "",
                  f"{ne['extension'].get('kind', 'multi-scale kernels')}: reach {ne['extension'].get('reach_px_before')} -> "
                  f"{ne['extension'].get('reach_px_after')} px; PSNR gain over an equally fine-tuned control on `{ne.get('split')}`: "
                  f"{gc['psnr_after'] - gc['psnr_before']:+.3f} dB (95 % CI [{gc['psnr_gain_ci95'][0]:+.3f}, {gc['psnr_gain_ci95'][1]:+.3f}]).", "",
                  format_table(ne), ""] + [f"![neural reach]({f})" for f in ne.get("figures", [])] + [""]
    if result.get("software"):
        lines += [f"_Software: {software_line(result['software'])}._", ""]
    with atomic_path(out / "report.md") as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
