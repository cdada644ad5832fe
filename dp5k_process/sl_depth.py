"""``dp5k sl-depth``: structured-light depth of camera 0 from any stereo rig's Gray-code images.

Input (a rig dp5k did not build; read and checked in :mod:`.sl_input`)::

    IMAGES/cam0/*   one camera's captures, IMAGES/cam1/* the other's, each sorted naturally by file name (im2 before
                    im10), in OpenCV GrayCodePattern's order: the pattern images (each pattern, then its inverse;
                    column bits then row bits, most significant first), then white, then black
    CALIBRATION     OpenCV FileStorage YAML/XML with K0, dist0, K1, dist1 (pixels of these images) and R, T taking
                    camera-0 coordinates to camera 1 (X1 = R X0 + T), T in --units

Any common image format: 8 or 16-bit PNG, JPEG, TIFF (also float), colour (converted to gray) or gray.

Processing is ``dp5k process``'s own: the same decoder (:mod:`.graycode`), the same check and refinement of the
extrinsics against the decoded matches (:mod:`.refine`), and the same per-scale triangulation, filters, projector
step and Eq. 3 filling (``pipeline.depth_for_camera``).

Nothing is silently wrong: OUT, the image counts and the calibration file are checked before any decoding (exit 3);
a baseline or scene depth that cannot be right (T in the wrong units) is refused naming the likely cause (exit 3);
a result below ``--min-coverage`` or a calibration the refinement could not make fit is still written, marked
``"quality": {"low": true, ...}`` in report.json and report.md, and the command exits 9 (``LowQualityResultError``).

Output (OUT, written atomically; an existing OUT/report.json is not overwritten without --overwrite)::

    depth_mm.png       16-bit depth of camera 0 in millimetres, 0 = invalid
    depth_m.tif        float32 depth in metres, NaN = invalid
    coverage.png       8-bit, 255 where camera 0 has depth
    depth_preview.png  the depth colour-mapped (near blue, far red, no depth black) with its range
    calibration.yaml   the calibration used (refined when the refinement applied), T in metres
    report.json        inputs, decoder settings, both calibrations and fits, coverages, quality, warnings, timings
    report.md          the same for people, with the preview
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import click
import cv2
import numpy as np

from calib.calibrate import StereoCalibration
from dp5k_common.cli_conventions import out_option, overwrite_option
from dp5k_common.errors import BadInputError, LowQualityResultError
from dp5k_common.io import finite_json, write_bytes_atomic, write_json_atomic, write_png16, write_tiff_float32
from dp5k_common.outdir import check_out_dir
from dp5k_common.preview import depth_preview
from dp5k_common.progress import progress
from dp5k_common.software import provenance

from .graycode import GrayCodeConfig, n_patterns
from .pipeline import ProcessConfig, depth_for_camera
from .refine import ViewCache, refine_stereo
from .sl_input import (
    check_count,
    check_scene_depth,
    decode_folder,
    decoder_config,
    full_scale_of,
    list_images,
    natural_key,
    read_calibration,
    read_gray,
)
from .sl_report import fmt, write_report_md

log = logging.getLogger(__name__)
MIN_COVERAGE = 0.10
"""Default ``--min-coverage``: the fraction of camera 0's pixels with depth below which the result is low quality."""
LIT_WARN = 0.25
"""Warn when fewer of camera 0's pixels than this pass the shadow test (|white - black| above its threshold)."""

__all__ = ["sl_depth", "sl_depth_command", "read_stereo_yaml", "natural_key", "list_images", "read_gray",
           "full_scale_of", "decoder_config", "decode_folder", "MIN_COVERAGE"]


def read_stereo_yaml(path: Path, units: str, sizes: tuple[tuple[int, int], tuple[int, int]]) -> StereoCalibration:
    """K0, dist0, K1, dist1, R, T from an OpenCV FileStorage file (T in ``units``) as a calibration in metres at
    the images' sizes (:func:`.sl_input.read_calibration`, then scaled to ``sizes``)."""
    return read_calibration(Path(path), units).at_sizes(sizes)


def _quality(report: dict[str, Any], min_coverage: float) -> dict[str, Any]:
    """``{"low": bool, "reasons": [...]}``: coverage under ``min_coverage``, or a refinement that did not make the
    matches fit."""
    reasons = []
    if report["depth_coverage"] < min_coverage:
        reasons.append(f"depth on {100 * report['depth_coverage']:.1f} % of camera 0's pixels (below --min-coverage "
                       f"{100 * min_coverage:g} %)")
    ref = report["refinement"]
    if ref.get("failed"):
        reasons.append(f"{ref.get('failed_why')} (median epipolar error "
                       f"{fmt(ref.get('epipolar_error_px'), '.2f')} px, {fmt(ref['gate_pass_rate'], '.1f', 100)} % of the "
                       f"matches in the ray gap)")
    return {"low": bool(reasons), "reasons": reasons, "min_coverage": min_coverage}


def _light_warnings(decs: dict[str, Any]) -> list[str]:
    """Warnings about the light: too few pixels lit above the shadow threshold (a dark scene, a short exposure, or
    white and black not the last two images), or lit pixels whose code does not decode."""
    out = []
    for cam, d in decs.items():
        lit = float(d.lit.mean())
        valid = float(d.at_scale(0)[2].mean())
        if lit < LIT_WARN:
            out.append(f"DARK: the projector lights only {100 * lit:.1f} % of {cam}'s pixels above the shadow threshold "
                       f"(|white - black| > {d.cfg.black_thr * 100:.3g} % of full scale; warning below "
                       f"{100 * LIT_WARN:g} %): the scene is dark, the exposure short or the projector dim, or the "
                       f"white and black images are not the last two")
        elif valid < 0.5 * lit:
            out.append(f"only {100 * valid / lit:.1f} % of {cam}'s lit pixels decode at full resolution: low contrast "
                       f"or blurred stripes (the coarser scales fill in where they can)")
    return out


def sl_depth(images: Path, calibration: Path, out: Path, projector: tuple[int, int], units: str = "mm",
             full_scale: float | None = None, thresholds: str = "auto", cfg: ProcessConfig = ProcessConfig(),
             overwrite: bool = False, min_coverage: float = MIN_COVERAGE) -> dict[str, Any]:
    """Depth of camera 0 (module docstring); returns the report, whose ``quality["low"]`` says whether the result
    is below its bounds (the CLI then exits 9).

    Raises:
        BadInputError: before any decoding: OUT cannot be written, holds a report (without ``overwrite``), an image
            folder is missing or holds the wrong number of images, the calibration file is not one or its baseline
            is implausible; after matching: a scene depth that cannot be right (T's units, another rig).
    """
    out, images = Path(out), Path(images)
    check_out_dir(out, create=False)
    if (out / "report.json").exists() and not overwrite:
        raise BadInputError("output already holds a report (use --overwrite)", where=out / "report.json")
    if not 0 <= min_coverage <= 1:
        raise BadInputError(f"--min-coverage must be a fraction in [0, 1], got {min_coverage}")
    files = {cam: list_images(images / cam) for cam in ("cam0", "cam1")}
    for cam, fl in files.items():
        check_count(fl, images / cam, projector)
    cal_file = read_calibration(Path(calibration), units)
    fs = full_scale_of(files["cam0"][0], full_scale)
    gcfg: GrayCodeConfig = decoder_config(thresholds, projector, full_scale_of(files["cam0"][0], None))
    check_out_dir(out, create=True)

    n_img = 2 * (n_patterns(*projector) + 2)
    with progress(total=n_img + 2, desc="sl-depth: decode", unit="step") as bar:
        t0 = time.perf_counter()
        decs, sizes = {}, {}
        for cam in ("cam0", "cam1"):
            decs[cam], sizes[cam] = decode_folder(files[cam], gcfg, fs, on_image=lambda: bar.update(1))
        timings = {"decode_s": time.perf_counter() - t0}
        st = cal_file.at_sizes((sizes["cam0"], sizes["cam1"]))
        bar.set_description("sl-depth: check the calibration")
        t0 = time.perf_counter()
        views_cache: ViewCache = {}  # code views shared by the check and the depth step
        st, refinement, warnings = refine_stereo(decs, st, cfg.tri, cfg.refine, where=str(images), cache=views_cache)
        timings["refine_s"] = time.perf_counter() - t0
        bar.update(1)
        md = refinement.get("match_depth_m")
        if md and refinement.get("gate_pass_rate", 0.0) >= 0.5:  # the depth of matches that fit the calibration
            check_scene_depth(md["median"], st.baseline_m, units, Path(calibration))
        warnings = _light_warnings(decs) + warnings
        bar.set_description("sl-depth: depth")
        t0 = time.perf_counter()
        depth_m, info = depth_for_camera(decs, "cam0", st, cfg, views_cache)
        timings["depth_s"] = time.perf_counter() - t0
        bar.update(1)
    valid = np.isfinite(depth_m)
    report: dict[str, Any] = {
        "images": str(images), "calibration_file": str(calibration), "units": units,
        "projector": list(projector), "image_size": {k: list(v) for k, v in sizes.items()},
        "decoder": {"thresholds": thresholds, "full_scale": fs, "white_thr": gcfg.white_thr,
                    "black_thr": gcfg.black_thr, "max_weak_bits": gcfg.max_weak_bits},
        "lit_fraction": {cam: float(d.lit.mean()) for cam, d in decs.items()},
        "decoded_fraction": {cam: float(d.at_scale(0)[2].mean()) for cam, d in decs.items()},
        "refinement": refinement, "depth_coverage": float(valid.mean()),
        "depth_m_median": float(np.median(depth_m[valid])) if valid.any() else None, **info, "timings": timings}
    report["quality"] = q = _quality(report, min_coverage)
    if report["depth_coverage"] < min_coverage:
        warnings.append(f"LOW COVERAGE: depth on only {100 * report['depth_coverage']:.1f} % of camera 0's pixels "
                        f"(--min-coverage {100 * min_coverage:g} %)")
    report["warnings"] = warnings
    write_png16(out / "depth_mm.png", np.clip(np.rint(np.nan_to_num(depth_m * 1000.0, nan=0.0)), 0, 65535).astype(np.uint16))
    write_tiff_float32(out / "depth_m.tif", depth_m)
    ok, buf = cv2.imencode(".png", (valid * 255).astype(np.uint8))
    if not ok:
        raise BadInputError("could not encode the coverage map", where=out / "coverage.png")
    write_bytes_atomic(out / "coverage.png", buf.tobytes())
    title = "LOW QUALITY" if q["low"] else "camera 0 depth"
    report["preview_range_m"] = list(depth_preview(depth_m, out / "depth_preview.png", title))
    st.save_yaml(out / "calibration.yaml")
    write_json_atomic(out / "report.json", finite_json({**report, "provenance": provenance()}))
    write_report_md(out / "report.md", report)
    return report


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise BadInputError(f"--projector must look like WxH (e.g. 1280x800), got {text!r}", where="--projector") from exc
    if w < 2 or h < 2:
        raise BadInputError(f"--projector must be at least 2x2, got {text!r}", where="--projector")
    return w, h


@click.command("sl-depth")
@click.argument("images", type=click.Path(path_type=Path))
@click.argument("calibration", type=click.Path(path_type=Path))
@out_option("Folder for the depth maps, previews and reports.", legacy_positional=True)
@click.option("--projector", required=True, help="Projector resolution WxH the Gray code was generated for.")
@click.option("--units", type=click.Choice(["mm", "m"]), default="mm", show_default=True, help="Units of T in CALIBRATION.")
@click.option("--full-scale", type=click.FloatRange(min=0, min_open=True), default=None,
              help="The images' full-scale value (default: 255 for 8-bit, 65535 for 16-bit, 1 for float); e.g. "
                   "4095 for 12-bit data in 16-bit files.")
@click.option("--thresholds", type=click.Choice(["auto", "opencv", "linear"]), default="auto", show_default=True,
              help="Decoder thresholds: opencv (5/255 and 40/255 of full scale, for gamma-encoded images), linear "
                   "(dp5k's linear-raw noise-based thresholds and neighbourhood tests); auto = opencv for 8-bit.")
@click.option("--fill-steps", type=click.IntRange(1, 4), default=3, show_default=True, help="Steps of Eq. 3 (as dp5k process).")
@click.option("--min-coverage", type=click.FloatRange(0, 1), default=MIN_COVERAGE, show_default=True,
              help="Fraction of camera 0's pixels that must get depth; below it the depth is still written, marked "
                   "low quality, and the command exits 9.")
@click.option("--no-refine", is_flag=True,
              help="Never refine the extrinsics: still checks them, and a calibration that does not fit exits 9.")
@overwrite_option("Replace the outputs of an earlier run in OUT (refused without it).")
def sl_depth_command(images: Path, calibration: Path, out: Path, projector: str, units: str, full_scale: float | None,
                     thresholds: str, fill_steps: int, min_coverage: float, no_refine: bool, overwrite: bool) -> None:
    """Structured-light depth of camera 0 from IMAGES/cam0 and IMAGES/cam1 (any stereo rig) into --out OUT.

    \b
    IMAGES/cam0/, IMAGES/cam1/: each camera's captures, sorted naturally (im2 before im10), in OpenCV
    GrayCodePattern's order: every pattern then its inverse, then white, then black. PNG, JPEG or TIFF,
    8/16-bit or float, colour or gray.
    CALIBRATION: OpenCV FileStorage with K0, dist0, K1, dist1, R, T (X1 = R X0 + T; T in --units).

    Uses dp5k process's decoder, filters, Eq. 3 filling and extrinsics refinement: when the matches' median
    epipolar error exceeds 0.5 px or most of their rays miss each other, R and T are refined from the matches (|T|
    kept) and the report gives the given calibration and both fits. Writes depth_mm.png (16-bit mm, 0 invalid),
    depth_m.tif (float32 m, NaN invalid), coverage.png, depth_preview.png, calibration.yaml, report.json and
    report.md.

    \b
    Exit codes: 3 bad input, checked before any decoding (OUT a file or unwritable, image counts, a calibration
    file that is not one, a baseline or scene depth that T's units cannot explain); 9 the depth was written but
    is low quality (coverage below --min-coverage, or a calibration the refinement could not make fit).
    """
    import dataclasses

    from .filters import FilterConfig
    from .refine import RefineConfig

    cfg = ProcessConfig(filt=dataclasses.replace(FilterConfig(), fill_steps=fill_steps),
                        refine=RefineConfig(fit=not no_refine))
    rep = sl_depth(images, calibration, out, _size(projector), units, full_scale, thresholds, cfg, overwrite, min_coverage)
    ref = rep["refinement"]
    line = (f"depth of cam0: {100 * rep['depth_coverage']:.1f} % of the pixels; median epipolar error "
            f"{fmt(ref['epipolar_error_px_given'], '.2f')} px and {fmt(ref['gate_pass_rate_charuco'], '.1f', 100)} % of the matches "
            f"in the {ref['gate_px']:g} px ray gap with the given calibration")
    if ref.get("applied"):
        line += (f"; refined ({ref['mode']}, {ref['rotation_change_deg']:.2f} deg): {fmt(ref['epipolar_error_px'], '.2f')} "
                 f"px, {fmt(ref['gate_pass_rate'], '.1f', 100)} %")
    click.echo(line + f"; written to {out} (report.md)")
    for w in rep["warnings"]:
        click.echo(f"WARNING: {w}", err=True)
    if rep["quality"]["low"]:
        raise LowQualityResultError("LOW QUALITY depth (written, marked in report.json 'quality'): "
                                    + "; ".join(rep["quality"]["reasons"]), where=out)
