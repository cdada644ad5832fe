"""``dp5k sl-depth``: structured-light depth of camera 0 from any stereo rig's Gray-code images.

Input (a rig dp5k did not build)::

    IMAGES/cam0/*   one camera's captures, IMAGES/cam1/* the other's, each sorted naturally by file name (im2 before
                    im10), in OpenCV GrayCodePattern's order: the pattern images (each pattern, then its inverse;
                    column bits then row bits, most significant first), then white, then black
    CALIBRATION     OpenCV FileStorage YAML/XML with K0, dist0, K1, dist1 (pixels of these images) and R, T taking
                    camera-0 coordinates to camera 1 (X1 = R X0 + T), T in --units

Any common image format: 8 or 16-bit PNG, JPEG, TIFF (also float), colour (converted to gray) or gray.

Processing is ``dp5k process``'s own: the same decoder (:mod:`.graycode`), the same check and refinement of the
extrinsics against the decoded matches (:mod:`.refine`), and the same per-scale triangulation, filters, projector
step and Eq. 3 filling (``pipeline.depth_for_camera``).

Output (OUT, written atomically; an existing OUT/report.json is not overwritten without --overwrite)::

    depth_mm.png     16-bit depth of camera 0 in millimetres, 0 = invalid
    depth_m.tif      float32 depth in metres, NaN = invalid
    coverage.png     8-bit, 255 where camera 0 has depth
    calibration.yaml the calibration used (refined when the refinement applied), T in metres
    report.json      inputs, decoder settings, both calibrations and coverages, per-scale coverage, warnings
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import cv2
import numpy as np
from numpy.typing import NDArray

from calib.calibrate import CameraCalibration, StereoCalibration
from dp5k_common.errors import BadInputError
from dp5k_common.io import (
    read_image_raw,
    write_bytes_atomic,
    write_json_atomic,
    write_png16,
    write_tiff_float32,
)

from .graycode import GrayCodeConfig, GrayDecode, decode_graycode, n_patterns
from .pipeline import ProcessConfig, depth_for_camera
from .refine import ViewCache, refine_stereo

log = logging.getLogger(__name__)
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")
UNITS_M = {"mm": 0.001, "m": 1.0}


def natural_key(name: str) -> list[Any]:
    """Sort key that orders digit runs by value: ``im2`` before ``im10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    """The image files of ``folder`` (hidden files skipped), sorted naturally."""
    if not folder.is_dir():
        raise BadInputError("image folder not found", where=folder)
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and not p.name.startswith(".")]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_gray(path: Path) -> NDArray[np.float32]:
    """An image as single-channel float32 in its stored units (colour -> luma, alpha dropped)."""
    img = read_image_raw(path)
    if img.ndim == 3:
        img = img[..., :3].astype(np.float32)
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.shape[2] == 3 else img[..., 0]
    if img.ndim != 2:
        raise BadInputError(f"expected a gray or colour image, got shape {img.shape}", where=path)
    return img.astype(np.float32)


def full_scale_of(path: Path, given: float | None) -> float:
    """The images' full-scale value: ``given``, else 255 for 8-bit, 65535 for 16-bit, 1 for float."""
    if given is not None:
        if not given > 0:
            raise BadInputError(f"--full-scale must be > 0, got {given}")
        return float(given)
    dt = read_image_raw(path).dtype
    return 255.0 if dt == np.uint8 else 65535.0 if dt == np.uint16 else 1.0


def decoder_config(thresholds: str, proj: tuple[int, int], dtype_full: float) -> GrayCodeConfig:
    """``opencv``: OpenCV's 5/255 and 40/255 of full scale (one weak bit tolerated); ``linear``: dp5k's linear-raw
    thresholds with the neighbourhood tests (:meth:`GrayCodeConfig.for_linear_raw`); ``auto``: opencv for 8-bit
    images, linear otherwise."""
    if thresholds == "auto":
        thresholds = "opencv" if dtype_full == 255.0 else "linear"
    if thresholds == "opencv":
        return GrayCodeConfig(proj[0], proj[1])
    if thresholds == "linear":
        return GrayCodeConfig.for_linear_raw(*proj)
    raise BadInputError(f"--thresholds must be auto, opencv or linear, got {thresholds!r}")


def decode_folder(files: list[Path], gcfg: GrayCodeConfig, full_scale: float) -> tuple[GrayDecode, tuple[int, int]]:
    """Decode one camera's image list (patterns, white, black), streamed from the files."""
    n = n_patterns(gcfg.proj_width, gcfg.proj_height)
    if len(files) != n + 2:
        raise BadInputError(f"{len(files)} images, expected {n + 2} for a {gcfg.proj_width}x{gcfg.proj_height} "
                            f"projector ({n} patterns and inverses, white, black)", where=files[0].parent if files else None)
    white, black = read_gray(files[n]), read_gray(files[n + 1])

    def load(i: int) -> NDArray[np.float32]:
        img = read_gray(files[i])
        if img.shape != white.shape:
            raise BadInputError(f"size {img.shape[1]}x{img.shape[0]} differs from the white image's "
                                f"{white.shape[1]}x{white.shape[0]}", where=files[i])
        return img

    load_checked: Callable[[int], NDArray[np.float32]] = load
    return decode_graycode(load_checked, white, black, full_scale, gcfg), (white.shape[1], white.shape[0])


def read_stereo_yaml(path: Path, units: str, sizes: tuple[tuple[int, int], tuple[int, int]]) -> StereoCalibration:
    """K0, dist0, K1, dist1, R, T from an OpenCV FileStorage file (T in ``units``) as a calibration in metres at
    the images' sizes (intrinsics scaled when the file states another ``image_width``/``image_height``)."""
    if not path.is_file():
        raise BadInputError("calibration file not found", where=path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # keep fs alive while reading nodes
    except cv2.error as exc:
        raise BadInputError(f"not an OpenCV FileStorage file ({exc.msg.strip()})", where=path) from exc
    try:
        if not fs.isOpened():
            raise BadInputError("not an OpenCV FileStorage file", where=path)
        m = {}
        for key, shape in (("K0", (3, 3)), ("dist0", None), ("K1", (3, 3)), ("dist1", None), ("R", (3, 3)), ("T", (3,))):
            v = fs.getNode(key).mat()
            if v is None:
                raise BadInputError(f"lacks '{key}' (needs K0, dist0, K1, dist1, R, T)", where=path)
            v = np.asarray(v, np.float64)
            if shape is not None and v.size != int(np.prod(shape)):
                raise BadInputError(f"'{key}' has {v.size} values, expected {int(np.prod(shape))}", where=path)
            m[key] = v.reshape(shape) if shape is not None else v.ravel()
        w_node, h_node = fs.getNode("image_width"), fs.getNode("image_height")
        stated = (int(w_node.real()), int(h_node.real())) if not w_node.empty() and not h_node.empty() else None
    finally:
        fs.release()
    if not np.allclose(m["R"] @ m["R"].T, np.eye(3), atol=1e-4):
        raise BadInputError("'R' is not a rotation matrix", where=path)
    cams = []
    for k, size in enumerate(sizes):
        cam = CameraCalibration(m[f"K{k}"], m[f"dist{k}"], stated or size)
        if stated and tuple(stated) != tuple(size):
            cam = cam.scaled(size[0] / stated[0], size[1] / stated[1])
        cams.append(cam)
    st = StereoCalibration(cams[0], cams[1], m["R"], m["T"] * UNITS_M[units], float("nan"))
    st.rectify()
    return st


def sl_depth(images: Path, calibration: Path, out: Path, projector: tuple[int, int], units: str = "mm",
             full_scale: float | None = None, thresholds: str = "auto", cfg: ProcessConfig = ProcessConfig(),
             overwrite: bool = False) -> dict[str, Any]:
    """Depth of camera 0 (module docstring); returns the report."""
    out = Path(out)
    if (out / "report.json").exists() and not overwrite:
        raise BadInputError("output already holds a report (use --overwrite)", where=out / "report.json")
    if units not in UNITS_M:
        raise BadInputError(f"--units must be mm or m, got {units!r}")
    t0 = time.perf_counter()
    files = {cam: list_images(Path(images) / cam) for cam in ("cam0", "cam1")}
    if not files["cam0"]:
        raise BadInputError("no images", where=Path(images) / "cam0")
    fs = full_scale_of(files["cam0"][0], full_scale)
    gcfg = decoder_config(thresholds, projector, full_scale_of(files["cam0"][0], None))
    decs, sizes = {}, {}
    for cam in ("cam0", "cam1"):
        decs[cam], sizes[cam] = decode_folder(files[cam], gcfg, fs)
    timings = {"decode_s": time.perf_counter() - t0}
    st = read_stereo_yaml(Path(calibration), units, (sizes["cam0"], sizes["cam1"]))
    t0 = time.perf_counter()
    views_cache: ViewCache = {}  # code views shared by the check and the depth step
    st, refinement, warnings = refine_stereo(decs, st, cfg.tri, cfg.refine, where=str(images), cache=views_cache)
    timings["refine_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    depth_m, info = depth_for_camera(decs, "cam0", st, cfg, views_cache)
    timings["depth_s"] = time.perf_counter() - t0
    valid = np.isfinite(depth_m)
    out.mkdir(parents=True, exist_ok=True)
    write_png16(out / "depth_mm.png", np.clip(np.rint(np.nan_to_num(depth_m * 1000.0, nan=0.0)), 0, 65535).astype(np.uint16))
    write_tiff_float32(out / "depth_m.tif", depth_m)
    ok, buf = cv2.imencode(".png", (valid * 255).astype(np.uint8))
    if not ok:
        raise BadInputError("could not encode the coverage map", where=out / "coverage.png")
    write_bytes_atomic(out / "coverage.png", buf.tobytes())
    st.save_yaml(out / "calibration.yaml")
    report = {"images": str(images), "calibration_file": str(calibration), "units": units,
              "projector": list(projector), "image_size": {k: list(v) for k, v in sizes.items()},
              "decoder": {"thresholds": thresholds, "full_scale": fs, "white_thr": gcfg.white_thr,
                          "black_thr": gcfg.black_thr, "max_weak_bits": gcfg.max_weak_bits},
              "decoded_fraction": {cam: float(d.at_scale(0)[2].mean()) for cam, d in decs.items()},
              "refinement": refinement, "warnings": warnings, "depth_coverage": float(valid.mean()),
              "depth_m_median": float(np.median(depth_m[valid])) if valid.any() else None, **info, "timings": timings}
    write_json_atomic(out / "report.json", report)
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
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--projector", required=True, help="Projector resolution WxH the Gray code was generated for.")
@click.option("--units", type=click.Choice(["mm", "m"]), default="mm", show_default=True, help="Units of T in CALIBRATION.")
@click.option("--full-scale", type=float, default=None,
              help="The images' full-scale value (default: 255 for 8-bit, 65535 for 16-bit, 1 for float); e.g. "
                   "4095 for 12-bit data in 16-bit files.")
@click.option("--thresholds", type=click.Choice(["auto", "opencv", "linear"]), default="auto", show_default=True,
              help="Decoder thresholds: opencv (5/255 and 40/255 of full scale, for gamma-encoded images), linear "
                   "(dp5k's linear-raw noise-based thresholds and neighbourhood tests); auto = opencv for 8-bit.")
@click.option("--fill-steps", type=click.IntRange(1, 4), default=3, show_default=True, help="Steps of Eq. 3 (as dp5k process).")
@click.option("--no-refine", is_flag=True, help="Never refine the extrinsics (still checks and warns).")
@click.option("--overwrite", is_flag=True, help="Replace the outputs of an earlier run in OUT.")
def sl_depth_command(images: Path, calibration: Path, out: Path, projector: str, units: str, full_scale: float | None,
                     thresholds: str, fill_steps: int, no_refine: bool, overwrite: bool) -> None:
    """Structured-light depth of camera 0 from IMAGES/cam0 and IMAGES/cam1 (any stereo rig) into OUT.

    \b
    IMAGES/cam0/, IMAGES/cam1/: each camera's captures, sorted naturally (im2 before im10), in OpenCV
    GrayCodePattern's order: every pattern then its inverse, then white, then black. PNG, JPEG or TIFF,
    8/16-bit or float, colour or gray.
    CALIBRATION: OpenCV FileStorage with K0, dist0, K1, dist1, R, T (X1 = R X0 + T; T in --units).

    Uses dp5k process's decoder, filters, Eq. 3 filling and extrinsics refinement: when the rays of most decoded
    matches miss each other, R and T are refined from the matches (|T| kept) and the report gives both
    calibrations. Writes depth_mm.png (16-bit mm, 0 invalid), depth_m.tif (float32 m, NaN invalid),
    coverage.png, calibration.yaml and report.json.
    """
    import dataclasses

    from .filters import FilterConfig
    from .refine import RefineConfig

    cfg = ProcessConfig(filt=dataclasses.replace(FilterConfig(), fill_steps=fill_steps),
                        refine=dataclasses.replace(RefineConfig(), trigger_pass_rate=0.0) if no_refine else RefineConfig())
    rep = sl_depth(images, calibration, out, _size(projector), units, full_scale, thresholds, cfg, overwrite)
    ref = rep["refinement"]
    line = (f"depth of cam0: {100 * rep['depth_coverage']:.1f} % of the pixels; matches passing the "
            f"{ref['gate_px']:g} px ray gap: {100 * ref['gate_pass_rate_charuco']:.1f} % with the given calibration")
    if ref.get("applied"):
        line += f", {100 * ref['gate_pass_rate']:.1f} % refined ({ref['rotation_change_deg']:.2f} deg)"
    click.echo(line + f"; written to {out}")
    for w in rep["warnings"]:
        click.echo(f"WARNING: {w}", err=True)
