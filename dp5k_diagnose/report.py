"""Write ``report.json`` and ``report.md`` (with PNG figures) of a diagnosis, atomically."""

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


def _save(fig: Any, path: Path) -> str:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, bbox_inches="tight", format="png")
    plt.close(fig)
    return path.name


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


def plot_disparity(disp: dict[str, Any], path: Path, title: str) -> str:
    fig, ax = plt.subplots(figsize=(5, 4))
    c = np.asarray(disp["coc_px"]); m = np.asarray(disp["measured_px"]); p = np.asarray(disp["predicted_px"])
    ax.scatter(c, m, s=6, alpha=0.5, label="measured")
    ax.scatter(c, p, s=6, alpha=0.5, label="model")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("signed CoC (px)"); ax.set_ylabel("R relative to L (px)")
    ax.set_title(title + ": DP disparity vs CoC", fontsize=9)
    ax.legend(fontsize=7)
    return _save(fig, path)


def plot_ratio(ratio: dict[str, Any], path: Path, title: str) -> str:
    fig, axes = plt.subplots(1, 2, figsize=(8, 3))
    for ax, k in zip(axes, ("x", "y")):
        t = ratio[k]
        nan = lambda v: [np.nan if x is None else x for x in v]  # noqa: E731
        ax.plot(t["bin_center"], nan(t["measured"]), "o-", label="measured")
        ax.plot(t["bin_center"], nan(t["predicted"]), "s--", label="model")
        ax.set_xlabel(f"field {k}"); ax.set_ylabel("mean L / mean R")
    axes[0].legend(fontsize=7)
    fig.suptitle(title + ": L/R brightness ratio across the field", fontsize=9)
    return _save(fig, path)


def plot_psfs(psfs: list[dict[str, Any]], path: Path, title: str) -> str:
    n = max(len(psfs), 1)
    fig, axes = plt.subplots(n, 4, figsize=(7, 1.8 * n), squeeze=False)
    for row, e in zip(axes, psfs):
        for ax, name, lab in zip(row, ("L", "R", "PL", "PR"), ("meas L", "meas R", "model L", "model R")):
            ax.imshow(np.asarray(e[name]), cmap="magma")
            ax.set_xticks([]); ax.set_yticks([])
            ax.set_title(f"{lab} c={e['coc_px']:.1f} {e['zone']}", fontsize=6)
    fig.suptitle(title + ": PSFs estimated from data (Wiener) per CoC bin and field zone", fontsize=8)
    return _save(fig, path)


def plot_findings(findings: list[dict[str, Any]], path: Path) -> str:
    fig, ax = plt.subplots(figsize=(7, 3))
    names = [f["effect"] for f in findings]
    vals = [f["effect_size"] for f in findings]
    colors = ["tab:red" if f["detected"] else "tab:gray" for f in findings]
    ax.barh(names[::-1], vals[::-1], color=colors[::-1])
    ax.set_xlabel("effect size (share of the error beyond noise removed; noise: excess variance)")
    ax.tick_params(labelsize=7)
    return _save(fig, path)


def sharp_reading_lines(sr: dict[str, Any] | None) -> list[str]:
    """report.md lines on how ``sharp`` was read where params.json does not say (none when every pair does)."""
    if not sr or sr.get("source") == "params.json":
        return []
    name = lambda n: "all-in-focus" if float(n) == 0 else f"f/{float(n):g}"  # noqa: E731
    line = f"`sharp` of {sr['pairs_without_key']} pairs without `sharp_f_number` read as **{name(sr['f_number'])}**"
    if sr.get("source") == "selected":
        tried = ", ".join(f"{name(k)}: MSE {v:.3g}, cause `{sr['causes'].get(k)}`" for k, v in sr["detect_mse"].items())
        line += f", the reading whose diagnosis predicts the detection pairs better ({tried})."
    else:
        line += " (`--sharp-f-number`)."
    return [line, ""]


def _num(v: float) -> str:
    return f"{v:.4g}"


def chain_text(causes: list[dict[str, Any]]) -> str:
    """`a` -> `b` -> ...: the causes' names in order."""
    return " -> ".join(f"`{c['name']}`" for c in causes)


def selection_lines(selection: dict[str, Any]) -> list[str]:
    """report.md's account of how the causes were chosen (report.json ``selection``): the screen, the effects the
    full model held and each elimination."""
    scr = selection.get("screen") or {}
    if not scr:
        return []
    share = scr.get("share", {})
    lines = ["How they were chosen: a first-order screen around the base model (share of the systematic error one "
             "Gauss-Newton step predicts each effect removes: " + ", ".join(f"`{k}` {v:.3f}" for k, v in sorted(share.items(), key=lambda kv: -kv[1]))
             + f"); the full model held {', '.join(f'`{n}`' for n in (selection.get('full_model') or {}).get('components', {})) or 'nothing'}."]
    gone = []
    for r in selection.get("rounds") or []:
        for t in r.get("refitted") or []:
            if not t["passed"]:
                gone.append(f"`{t['effect']}` (given the others {t['effect_size']:+.3f}, p {t['p_value']:.2g})")
                break
    if gone:
        lines[-1] += " Removed, weakest first, when the detection pairs did not need them: " + ", ".join(gone) + "."
    return lines + [""]


def suspects_lines(result: dict[str, Any]) -> list[str]:
    """report.md's look-alikes and suspects (report.json ``lookalikes``, ``suspects``)."""
    lines: list[str] = []
    for g in result.get("lookalikes") or []:
        first, others = g["names"][0], g["names"][1:]
        for o, cap, cc, lost, kind in zip(others, g["captures"], g["correlation"], g["effect_size_lost"], g["kinds"]):
            if kind == "also":
                lines += [f"**`{first}` may hide `{o}`.** Alone `{o}` would explain enough of the error to be named, but nothing "
                          f"beyond what `{first}` explains (first-order correlation of their effects {cc:.2f}): this data cannot tell "
                          f"whether `{o}` is present too. To tell, capture {cap}.", ""]
                continue
            simpler = f" `{first}` is named: it fits fewer parameters." if o in (g.get("fewer_parameters_than") or []) else ""
            lines.append(f"**`{first}` or `{o}`: indistinguishable on this data.** Refitted in `{first}`'s place, `{o}` explains what it "
                         f"explained and predicts the detection pairs as well (loses {lost:+.3f} of the systematic error; first-order "
                         f"correlation of their effects {cc:.2f}).{simpler} To tell them apart, capture {cap}.")
            lines.append("")
    for sp in result.get("suspects") or []:
        lo, hi = sp["gain_ci_db"]
        lines += [f"**Suspect, not named: `{sp['name']}`** ({sp['explanation']}): {sp['why']} (gain {sp['gain_db']:+.3f} dB).", ""]
    return lines


def causes_lines(result: dict[str, Any]) -> list[str]:
    """report.md's chain of causes (report.json ``causes``), the measured noise model and what the fit saw."""
    lines = ["## Causes, in order", "",
             "Each cause was tested given every other cause (effect size: the share of the base model's systematic error "
             "that removing it from the final model gives back on the detection pairs, the others refitted; p: "
             "signed-rank test over pairs, Hochberg-corrected over the causes). A cause is named only when its held-out gain "
             "given the others has a 95 % CI above 0; otherwise it is a suspect. Held-out PSNR gains, 95 % bootstrap CI "
             "over the 32 px tiles within each held-out pair (what these captures show beyond their noise; in brackets "
             "after *pairs*, the CI over pairs: how the gain varies from capture to capture): *given the others* is what the cause adds to a model holding every other cause (the final model "
             "against it without the cause, refitted), *step* what it adds over the steps before it; the step gains add "
             "up to the cumulative one. Parameters are those of the final model, all chosen effects refitted "
             "together, with 95 % intervals clustered over the fit pairs. `noise` comes last: a prediction is an "
             "expectation, so modelling noise cannot raise PSNR.", ""]
    causes = result.get("causes") or []
    if not causes:
        lines += ["No effect of the vocabulary is significant: `none`.", ""]
    else:
        lines += ["| step | effect | effect size | p-value | gain given the others (dB) [95 % CI] | step gain (dB) [95 % CI] | cumulative (dB) | parameters [95 % interval] |",
                  "|---|---|---|---|---|---|---|---|"]
        for c in causes:
            iv = c.get("param_intervals", {})
            par = ", ".join(f"{k}={_num(v)}" + (f" [{_num(iv[k][0])}, {_num(iv[k][1])}]" if k in iv else "")
                            for k, v in c["params"].items() if isinstance(v, float))
            lo, hi = c["gain_ci_db"]
            plo, phi = c.get("gain_ci_pairs_db", (lo, hi))
            slo, shi = c["step_gain_ci_db"]
            lines.append(f"| {c['step']} | `{c['name']}` | {c['effect_size']:.3f} | {c['p_value']:.2g} | {c['gain_db']:+.3f} [{lo:+.3f}, {hi:+.3f}] "
                         f"(pairs [{plo:+.3f}, {phi:+.3f}]) "
                         f"| {c['step_gain_db']:+.3f} [{slo:+.3f}, {shi:+.3f}] | {c['cumulative_gain_db']:+.3f} | {par} |")
        lines.append("")
    lines += suspects_lines(result)
    lines += selection_lines(result.get("selection") or {})
    nm = result.get("noise_model") or {}
    if nm.get("measured"):
        iv = nm.get("intervals", {})
        rng = lambda k: f" [{_num(iv[k][0])}, {_num(iv[k][1])}]" if k in iv else ""  # noqa: E731
        lines += [f"Measured view noise (against the final model): variance = shot_var I + read_sigma^2 with shot_var "
                  f"{_num(nm['shot_var'])}{rng('shot_var')}, read_sigma {_num(nm['read_sigma'])}{rng('read_sigma')} (linear units), "
                  f"{nm['variance_ratio']:.2f}{rng('variance_ratio')} x the nominal sensor's (shot_var {_num(nm['nominal']['shot_var'])}, "
                  f"read_sigma {_num(nm['nominal']['read_sigma'])}); excess {'significant' if nm['excess_significant'] else 'not significant'} "
                  f"(p {nm['excess_p_value']:.2g}).", ""]
    cov = result.get("fit_coverage") or {}
    if cov:
        x0, x1, y0, y1 = cov["field_box"]
        lines += [f"The fits saw {cov['pairs']} pairs of {cov['scenes']} scenes ({cov['crops']} crops), {cov['field_zones']} of "
                  f"{cov['field_zones_of']} field zones, field x {x0:+.2f}..{x1:+.2f}, y {y0:+.2f}..{y1:+.2f}; field-dependent "
                  f"ranges are given over that field only.", ""]
    return lines


def write_report(out: Path, result: dict[str, Any], analysis: dict[str, Any]) -> None:
    """``out/report.json`` (the contract of issue 7 plus analysis tables) and ``out/report.md`` with figures."""
    out.mkdir(parents=True, exist_ok=True)
    figs = {}
    for stage in ("before", "after"):
        a = analysis.get(stage)
        if not a:
            continue
        figs[f"residuals_{stage}"] = plot_residuals(a["residuals"], out / f"residuals_{stage}.png", stage)
        figs[f"disparity_{stage}"] = plot_disparity(a["disparity"], out / f"disparity_{stage}.png", stage)
        figs[f"lr_ratio_{stage}"] = plot_ratio(a["lr_ratio"], out / f"lr_ratio_{stage}.png", stage)
        if a.get("psfs"):
            figs[f"psfs_{stage}"] = plot_psfs(a["psfs"], out / f"psfs_{stage}.png", stage)
    figs["findings"] = plot_findings(result["findings"], out / "findings.png")
    full = dict(result)
    full["analysis"] = analysis
    full["figures"] = figs
    write_json_atomic(out / "report.json", full)
    g = result["gain"]
    lines = [
        f"# dp5k diagnose: `{result['model']}` on `{result['dataset']}`",
        "",
        f"**Cause: `{result['cause']}`**" + (f": {result['findings'][0]['explanation']}." if result["cause"] != "none" else ": no effect of the vocabulary is significant."),
        "",
        *([f"**Every cause, in order: {chain_text(result['causes'])}**", ""] if len(result.get("causes") or []) > 1 else []),
        f"Base model fitted on train: {json.dumps({k: round(v, 4) for k, v in result.get('base_params', {}).items()})}",
        "",
        *sharp_reading_lines(result.get("sharp_reading")),
        *causes_lines(result),
        "## Every effect of the vocabulary",
        "",
        "Effect size: the share of the base model's systematic error (its squared error less the views' measured "
        "white noise) that the effect removes on detection pairs no fit saw, given the other effects of the model "
        "it was tested in (named: the final model; eliminated: the model it was removed from); screened out: the "
        "share a first-order step predicted; `noise`: the excess noise variance over a nominal sensor's.",
        "",
        "| effect | named | stage | effect size | statistic (z) | p-value | parameters | explanation |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f in result["findings"]:
        par = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in f["params"].items())
        lines.append(f"| {f['effect']} | {'yes' if f['detected'] else 'no'} | {f.get('stage', '')} | {f['effect_size']:.4f} | {f['statistic']:.2f} | "
                     f"{f['p_value']:.2e} | {par} | {f['explanation']} |")
    lines += ["", f"![findings]({figs['findings']})", "", f"## Gain on the held-out `{g['split']}` split ({g.get('n_pairs', '?')} pairs)", "",
              "Masked over the predictable pixels (valid, out of blur reach of the frame border and of depth edges, as in "
              "the fit and the tests); the last columns take every valid pixel.", "",
              "| metric | before | after | before (all valid) | after (all valid) |", "|---|---|---|---|---|"]
    av = g.get("all_valid", {})
    for label, key, fmt in (("masked PSNR (dB)", "psnr", ".3f"), ("masked SSIM", "ssim", ".4f"), ("masked MAE", "mae", ".5f")):
        cells = [format(d[f"{key}_{w}"], fmt) if f"{key}_{w}" in d else "-" for d in (g, av) for w in ("before", "after")]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", f"PSNR gain {g['psnr_after'] - g['psnr_before']:+.3f} dB, 95 % bootstrap CI over pairs [{g['psnr_gain_ci95'][0]:+.3f}, {g['psnr_gain_ci95'][1]:+.3f}]"
              + (f"; over all valid pixels {av['psnr_after'] - av['psnr_before']:+.3f} dB [{av['psnr_gain_ci95'][0]:+.3f}, {av['psnr_gain_ci95'][1]:+.3f}]" if av else "")
              + ".", ""]
    if "note" in g:
        lines += [g["note"], ""]
    for stage in ("before", "after"):
        a = analysis.get(stage)
        if not a:
            continue
        d = a["disparity"]
        lines += [f"## What the {'base' if stage == 'before' else 'extended'} model gets wrong ({stage})", "",
                  f"![residuals]({figs[f'residuals_{stage}']})", "",
                  f"Disparity vs CoC: measured slope {d.get('measured_slope_px_per_coc', float('nan')):.4f} px/px, model {d.get('predicted_slope_px_per_coc', float('nan')):.4f} px/px over {d['n_tiles']} tiles.", "",
                  f"![disparity]({figs[f'disparity_{stage}']}) ![ratio]({figs[f'lr_ratio_{stage}']})", ""]
        if f"psfs_{stage}" in figs:
            lines += ["| CoC (px) | zone | tiles | measured L-R separation (px) | model separation (px) |", "|---|---|---|---|---|"]
            for e in a["psfs"]:
                lines.append(f"| {e['coc_px']:.2f} | {e['zone']} | {e['n_tiles']} | {e['measured_separation_px']:.3f} | {e['model_separation_px']:.3f} |")
            lines += ["", f"![psfs]({figs[f'psfs_{stage}']})", ""]
    ne = result.get("neural_extension")
    if ne:
        from .neural_reach import format_table

        gc = ne["gain_vs_control"]
        lines += ["## The learned model's reach and its structural extension", "",
                  f"{ne['extension'].get('kind', 'multi-scale kernels')}: reach {ne['extension'].get('reach_px_before')} -> "
                  f"{ne['extension'].get('reach_px_after')} px; the extended network starts equal to the checkpoint "
                  f"(max difference {ne['extension'].get('init_max_abs_diff')}) and is fine-tuned beside an equally fine-tuned control.", "",
                  f"PSNR gain over the control on `{ne.get('split')}`: {gc['psnr_after'] - gc['psnr_before']:+.3f} dB "
                  f"(95 % CI [{gc['psnr_gain_ci95'][0]:+.3f}, {gc['psnr_gain_ci95'][1]:+.3f}]).", "",
                  format_table(ne), ""] + [f"![neural reach]({f})" for f in ne.get("figures", [])] + [""]
    if result.get("software"):
        lines += [f"_Software: {software_line(result['software'])}._", ""]
    with atomic_path(out / "report.md") as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
