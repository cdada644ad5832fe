"""Assemble ``OUT/report.html`` from the stages' outputs: what a researcher checks first.

Numbers are read from the stages' own result files (evaluate's ``metrics.json``, diagnose's ``report.json``,
validate-depth's ``report.json``) or recomputed here against the studio's ground truth (depth accuracy and
focus distance of the processed dataset); ``report.json`` keeps every number shown.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.dataset import DatasetReader
from dp5k_common.io import read_image_raw, read_json

from . import figures
from .report import Report

if TYPE_CHECKING:
    from .pipeline import DemoScale


def truth_depth_at(raw_scene: Path, camera: str, size: tuple[int, int], *, lit_only: bool = False) -> NDArray[np.float64]:
    """The studio's true depth (mm) of ``camera`` resampled to the output ``size`` (W, H).

    Each output pixel covers a block of raw pixels (half-size output: 2 x 2); the block's median is its truth,
    0 where any of the block is empty (no surface) or, with ``lit_only``, not lit by the projector (the
    pixels structured light can measure at all: seen by this camera and the projector).
    """
    depth = read_image_raw(raw_scene / "ground_truth" / f"{camera}_depth_mm.png").astype(np.float64)
    if lit_only:
        lit = np.isfinite(np.load(raw_scene / "ground_truth" / f"{camera}_proj_xy.npy")).all(axis=2)
        depth = np.where(lit, depth, 0.0)
    H_raw, W_raw = depth.shape
    W, H = size
    if (W_raw % W, H_raw % H) == (0, 0):
        fy, fx = H_raw // H, W_raw // W
        blocks = depth.reshape(H, fy, W, fx).transpose(0, 2, 1, 3).reshape(H, W, fy * fx)
        med = np.median(blocks, axis=2)
        return np.where(blocks.min(axis=2) > 0, med, 0.0)
    return cv2.resize(depth, (W, H), interpolation=cv2.INTER_NEAREST)


def depth_accuracy(processed: Path, raw: Path) -> list[dict[str, Any]]:
    """Per scene and camera: median |relative depth error| on valid pixels, coverage of the pixels with true
    depth, and the focus distance (Eq. 5) against the studio's true focus distance."""
    reader = DatasetReader(processed)
    rows: list[dict[str, Any]] = []
    seen: set[tuple[str, str]] = set()
    for pid in reader.ids():
        params = reader.params(pid)
        key = (params.scene, params.camera)
        if key in seen:
            continue
        seen.add(key)
        pair = reader.load(pid)
        truth = truth_depth_at(raw / params.scene, params.camera, params.image_size)
        lit = truth_depth_at(raw / params.scene, params.camera, params.image_size, lit_only=True) > 0
        both = (truth > 0) & pair.valid
        rel = np.abs(pair.depth_mm[both] - truth[both]) / truth[both]
        truth_json = read_json(raw / params.scene / "ground_truth" / "truth.json")
        f_true_mm = 1000.0 * truth_json["cameras"][params.camera]["focus_distance_true_m"]
        rows.append({
            "scene": params.scene,
            "camera": params.camera,
            "median_rel_depth_err_pct": float(np.median(rel) * 100) if rel.size else float("nan"),
            "coverage_pct": float((lit & pair.valid).sum() / max(1, lit.sum()) * 100),
            "focus_mm": params.focus_distance_mm,
            "focus_true_mm": f_true_mm,
            "focus_err_pct": abs(params.focus_distance_mm - f_true_mm) / f_true_mm * 100,
            "pair_id": pid,
        })
    return rows


def _signature_row(effect: str, sig: dict, named: bool) -> list:
    """One row of the demo's signature table: an effect's strongest value (over its minimum) and its interval."""
    vals = [v for v in sig.get("values") or [] if v.get("value") is not None]
    if not vals:
        return [effect, sig.get("unmeasured") or "not measured", "-", "-", False, named]
    v = max(vals, key=lambda v: abs(v["value"]) / v["min_effect"])
    lo, hi = v["interval95"]
    return [effect, f"{v['name']} {v['value']:+.3g} {v['unit']}", f"[{lo:+.3g}, {hi:+.3g}]", v["min_effect"], sig["differs"], named]


def _copy(src: Path, out: Path, rel: str) -> str:
    dst = out / rel
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    return rel


def build_report(out: Path, scale: DemoScale, records: dict[str, dict[str, Any]], hidden: str) -> Path:
    """Write ``out/report.html`` (+ ``report.json``, figures under ``out/report-figures``) and return its path."""
    figs = out / "report-figures"
    rep = Report(
        "dp5k demo: the DP5K pipeline on the virtual studio",
        f"Scale '{scale.name}'. Everything below ran through the same code paths as the real commands: simulated "
        "Canon bodies over PTP, a simulated EPSON projector over ESC/VP21, the virtual studio as the world. "
        "The studio knows the truth, so depth, focus distance and the hidden effect can be checked.",
    )

    # 1. capture
    raw = out / "raw"
    s = rep.section("1. Captured raw sessions")
    manifest = read_json(raw / scale.scenes[0] / "manifest.json")
    counts: dict[str, int] = {}
    for f in manifest["files"]:
        counts[f["kind"]] = counts.get(f["kind"], 0) + 1
    s.table("file_counts", ["kind", "files (2 bodies)"], [[k, v] for k, v in sorted(counts.items())],
            "Files per scene (paper: 10 DP + 2 sharp raws, 6 ChArUco, 92 structured light).")
    for scene in scale.scenes:
        figures.capture_sheet(raw / scene, figs / f"capture_{scene}.png")
        s.figure(f"report-figures/capture_{scene}.png", f"Raw previews of scene '{scene}' (both bodies).")

    # 2. processing
    processed = out / "processed"
    s = rep.section("2. Processed dataset and accuracy against ground truth")
    for skip in records["process"]["result"].get("skipped", []):
        s.text(f"Scene '{skip['scene']}' was skipped by processing, as a real capture would be: {skip['reason']}")
    acc = depth_accuracy(processed, raw)
    s.table("depth_accuracy", ["scene", "camera", "median |rel. depth err| (%)", "coverage (%)", "focus F (mm)",
                               "true F (mm)", "focus err (%)"],
            [[a["scene"], a["camera"], a["median_rel_depth_err_pct"], a["coverage_pct"], a["focus_mm"],
              a["focus_true_mm"], a["focus_err_pct"]] for a in acc],
            "Targets: median depth error <= 0.5 % on valid pixels; coverage >= 95 % of the pixels this camera and the "
            "projector see (pixels the other camera cannot see are measured through the self-calibrated projector); "
            "focus distance (Eq. 5) within 0.5 % of the studio's truth.", digits=4)
    reader = DatasetReader(processed)
    for a in acc[:2]:
        pair = reader.load(a["pair_id"])
        truth = truth_depth_at(raw / a["scene"], a["camera"], pair.params.image_size)
        name = f"depth_coc_{a['pair_id']}.png"
        figures.depth_coc_figure(pair, figs / name, truth)
        s.figure(f"report-figures/{name}", f"{a['pair_id']}: depth and signed CoC with colour bars, and the depth error.")
    for scene in sorted({a["scene"] for a in acc}):
        sheet = processed / "reports" / scene / "contact_sheet.png"
        if sheet.is_file():
            s.figure(_copy(sheet, out, f"report-figures/contact_{scene}.png"), f"Processing contact sheet of '{scene}' (sharp, left, right, depth, CoC).")

    # 3. depth validation
    s = rep.section("3. Depth validation against a ChArUco wall (Eq. 4)")
    vrep = read_json(out / "validate-depth" / "report.json")
    rows = [[k, v] for k, v in vrep.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    s.table("validate_depth", ["quantity", "value"], rows, "Paper: 0.59 %; RealSense D415: 2 %.", digits=4)
    res = out / "validate-depth" / "residuals.png"
    if res.is_file():
        s.figure(_copy(res, out, "report-figures/wall_residuals.png"), "Point-to-plane residuals of the wall.")

    # 4. simulators
    s = rep.section("4. DP simulators compared (the paper's Table 2)")
    s.text(f"Training data: studio scenes with realistic effects ({', '.join(records['studio_train']['result']['effects'])}); "
           f"{scale.epochs} training epochs on the CPU of a U-Net {scale.base_channels} channels wide at its first level "
           "(a short run; the paper trains a 64-channel one for 100 epochs on 3850 pairs).")
    for name in ("studio", "processed"):
        ev = out / f"evaluate-{name}"
        metrics = read_json(ev / "metrics.json")
        sims = metrics["simulators"]
        header = ["metric", *sims]
        rows = [[m, *[metrics["means"][k][m] for k in sims]] for m in ("mae", "psnr", "ssim")]
        s.table(f"evaluate_{name}", header, rows,
                f"Masked metrics on the {metrics['split']} split of the {name} dataset ({len(metrics['pairs'])} pairs); "
                "the base model's gain and rim softness fitted on the train split.", digits=4)
        for fig in sorted((ev / "figures").glob("*.png"))[:1]:
            s.figure(_copy(fig, out, f"report-figures/eval_{name}_{fig.name}"), f"Views and error maps per simulator ({name}, {fig.stem}).")

    # 5. diagnosis
    s = rep.section("5. Diagnosis: what a simulator gets wrong, and why")
    for name in ("base", "neural"):
        drep = read_json(out / f"diagnose-{name}" / "report.json")
        g = drep["gain"]
        s.text(f"<b>{name} model</b>: named cause <b>{drep['cause']}</b>; PSNR {g['psnr_before']:.2f} -> {g['psnr_after']:.2f} dB "
               f"(gain 95 % CI [{g['psnr_gain_ci95'][0]:.2f}, {g['psnr_gain_ci95'][1]:.2f}] dB), SSIM {g['ssim_before']:.4f} -> "
               f"{g['ssim_after']:.4f}, MAE {g['mae_before']:.4f} -> {g['mae_after']:.4f} on the held-out split's predictable pixels"
               + (f" (all valid pixels: PSNR {g['all_valid']['psnr_before']:.2f} -> {g['all_valid']['psnr_after']:.2f} dB)" if "all_valid" in g else "")
               + ".", raw_html=True)
        named = {c["name"] for c in drep["causes"]}
        s.table(f"diagnose_{name}", ["effect", "signature (measured - simulator)", "95 % interval", "minimum", "differs", "named"],
                [_signature_row(e, sig, e in named) for e, sig in drep["signatures"].items()],
                f"Every effect's signature: the measured PSF atlas against the {name} model's, on the same pairs.", digits=3)
        s.data[f"diagnose_{name}_gain"] = g
        s.data[f"diagnose_{name}_cause"] = drep["cause"]
        pngs = sorted((out / f"diagnose-{name}").rglob("*.png"))
        for png in pngs[:2]:
            s.figure(_copy(png, out, f"report-figures/diag_{name}_{png.name}"), f"{name} model: {png.stem.replace('_', ' ')}.")
    verdict = "found it" if read_json(out / "diagnose-base" / "report.json")["cause"] == hidden else "did NOT find it"
    s.text(f"The hidden effect was <b>{hidden}</b> (drawn from the demo's seed); the base-model diagnosis {verdict}.", raw_html=True)
    s.data["hidden_effect"] = hidden

    # 6. synthesis
    s = rep.section("6. Synthesized DP pairs from RGBD frames")
    syn = DatasetReader(out / "synthesized")
    pairs = [syn.load(pid) for pid in syn.ids()[:3]]
    figures.synthesized_figure(pairs, figs / "synthesized.png")
    s.table("synthesized", ["pair", "f-number", "focus (mm)", "max |CoC| (px)"],
            [[p.pair_id, p.params.f_number, p.params.focus_distance_mm, float(np.nanmax(np.abs(p.coc_px)))] for p in pairs])
    s.figure("report-figures/synthesized.png", "Neural DP Simulator output on RGBD frames.")

    # 7. timings
    s = rep.section("7. Time per stage")
    stage_times = [(r["title"], float(r["seconds"])) for r in records.values()]
    s.table("timings", ["stage", "seconds", "reused from an earlier run"],
            [[r["title"], r["seconds"], r["reused"]] for r in records.values()], digits=4)
    figures.timings_figure(stage_times, figs / "timings.png")
    s.figure("report-figures/timings.png", "Seconds per stage (this run; reused stages show their first run's time).")
    return rep.write(out)
