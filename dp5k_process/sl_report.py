"""``report.md`` of ``dp5k sl-depth``: what was measured, how the calibration fitted, and whether to trust it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dp5k_common.io import write_bytes_atomic


def _pose(p: dict[str, Any] | None) -> str:
    if not p:
        return "-"
    rv = ", ".join(f"{v:.3f}" for v in p["rotation_vector_deg"])
    t = ", ".join(f"{1000 * v:.1f}" for v in p["T_m"])
    return f"rotation vector ({rv}) deg, T ({t}) mm"


def fmt(v: Any, spec: str, scale: float = 1.0) -> str:
    """``v * scale`` formatted with ``spec``, or "-" for None (a value JSON could not hold)."""
    return "-" if v is None else format(v * scale, spec)


def write_report_md(path: Path, rep: dict[str, Any]) -> None:
    """Write the report for people (the numbers of ``report.json``, the verdict first)."""
    q, ref = rep["quality"], rep["refinement"]
    lines = ["# Structured-light depth (dp5k sl-depth)", ""]
    if q["low"]:
        lines += ["**LOW QUALITY: do not use this depth unseen.** " + "; ".join(q["reasons"]) + ".", ""]
    else:
        lines += [f"Depth on {100 * rep['depth_coverage']:.1f} % of camera 0's pixels; the calibration fits the "
                  f"images (median epipolar error {fmt(ref.get('epipolar_error_px'), '.2f')} px).", ""]
    lines += ["![depth](depth_preview.png)", "",
              f"Median depth {fmt(rep['depth_m_median'], '.4g')} m (preview range {rep['preview_range_m'][0]:.3g} .. "
              f"{rep['preview_range_m'][1]:.3g} m). Images `{rep['images']}` ({rep['image_size']['cam0'][0]} x "
              f"{rep['image_size']['cam0'][1]} px), projector {rep['projector'][0]} x {rep['projector'][1]}, "
              f"calibration `{rep['calibration_file']}` (T in {rep['units']}).", ""]
    if rep["warnings"]:
        lines += ["## Warnings", ""] + [f"* {w}" for w in rep["warnings"]] + [""]
    lines += ["## Light and decoding", "", "| | cam0 | cam1 |", "|---|---|---|",
              "| lit (above the shadow threshold) | " + " | ".join(f"{100 * rep['lit_fraction'][c]:.1f} %" for c in ("cam0", "cam1")) + " |",
              "| decoded at full resolution | " + " | ".join(f"{100 * rep['decoded_fraction'][c]:.1f} %" for c in ("cam0", "cam1")) + " |",
              "", "Coverage per projector scale (camera 0): " + ", ".join(
                  f"{s} {100 * c:.1f} %" for s, c in zip(rep.get("fill_scales", []), rep.get("per_scale_coverage", []))), ""]
    lines += ["## Calibration against the structured light", "",
              f"{ref.get('matches', 0)} matches at scale {ref.get('probe_scale', '-')}; a fitting calibration leaves a "
              f"median epipolar error of 0.1-0.2 px and passes nearly all of them through the {ref.get('gate_px', 1.5):g} "
              f"px ray gap.", "",
              "| calibration | median / p90 epipolar error (px) | in the ray gap | pose |", "|---|---|---|---|",
              f"| given | {fmt(ref.get('epipolar_error_px_given'), '.2f')} / {fmt(ref.get('epipolar_p90_px_given'), '.2f')} "
              f"| {fmt(ref.get('gate_pass_rate_charuco'), '.1f', 100)} % | {_pose(ref.get('charuco'))} |"]
    for key, label in (("three_parameters", "three parameters"), ("five_parameters", "five parameters (free)")):
        f = ref.get(key)
        if f:
            used = " **(used)**" if ref.get("applied") and ref.get("mode") == label.split(" (")[0] else ""
            lines.append(f"| {label}{used} | {fmt(f.get('epipolar_error_px'), '.2f')} / "
                         f"{fmt(f.get('epipolar_p90_px'), '.2f')} | {fmt(f.get('gate_pass_rate'), '.1f', 100)} % | "
                         f"{_pose(f)} |")
    five = ref.get("five_parameters")
    if five:
        ratio = five.get("depth_ratio_five_to_three")
        lines += ["", f"Five parameters: depth {fmt(None if ratio is None else ratio - 1, '+.2f', 100)} % against the "
                      f"three-parameter fit; its two extra parameters leave {fmt(five.get('depth_sd_pct'), '.2f')} % of "
                      f"depth-scale uncertainty (standard deviation); scene flatness {fmt(five.get('flatness'), '.3f')}"
                  + (f"; not used: {five['why_not']}" if five.get("why_not") else "") + "."]
    if not ref.get("triggered", False):
        lines += ["", "Not refined: the given calibration fits the matches."]
    lines += ["", f"Timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in rep["timings"].items()) + "."]
    write_bytes_atomic(path, ("\n".join(lines) + "\n").encode())
