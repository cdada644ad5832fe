"""``dp5k sl-depth``'s inputs, checked before any decoding: image folders in OpenCV GrayCodePattern's order and an
OpenCV FileStorage calibration (YAML or XML), with the checks that catch what would otherwise give a silently wrong
or empty depth map (a garbage file, T in the wrong units).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.calibrate import CameraCalibration, StereoCalibration
from dp5k_common.errors import BadInputError
from dp5k_common.io import read_image_raw

from .graycode import GrayCodeConfig, GrayDecode, decode_graycode, n_patterns

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")
UNITS_M = {"mm": 0.001, "m": 1.0}
BASELINE_RANGE_M = (0.002, 50.0)
"""Plausible stereo (or camera-projector) baselines |T|, metres: two bodies side by side are at least a few mm
apart; beyond 50 m no projector lights the scene. Outside it the units of T are almost surely wrong."""
SCENE_DEPTH_RANGE_M = (0.02, 1000.0)
"""Plausible median depths of a projector-lit scene, metres (checked on the triangulated matches)."""
DEPTH_PER_BASELINE = (0.1, 1000.0)
"""Plausible median scene depth / baseline: closer than a tenth of the baseline the two views barely overlap;
farther than 1000 baselines the rays meet at under 0.06 deg and depth is noise. The ratio does not depend on the
units of T (depth scales with T), so outside it the calibration does not belong to these images."""


def natural_key(name: str) -> list[Any]:
    """Sort key that orders digit runs by value: ``im2`` before ``im10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_images(folder: Path) -> list[Path]:
    """The image files of ``folder`` (hidden files skipped), sorted naturally."""
    if not folder.is_dir():
        raise BadInputError("image folder not found", where=folder)
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and not p.name.startswith(".")]
    return sorted(files, key=lambda p: natural_key(p.name))


def check_count(files: list[Path], folder: Path, proj: tuple[int, int]) -> None:
    """``n_patterns + 2`` images for the projector, or a one-line error naming the folder and both counts."""
    n = n_patterns(*proj)
    if len(files) != n + 2:
        raise BadInputError(f"{len(files)} images, expected {n + 2} for a {proj[0]}x{proj[1]} projector ({n} patterns "
                            f"and inverses, white, black)", where=folder)


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


def decode_folder(files: list[Path], gcfg: GrayCodeConfig, full_scale: float,
                  on_image: Callable[[], None] | None = None) -> tuple[GrayDecode, tuple[int, int]]:
    """Decode one camera's image list (patterns, white, black), streamed from the files; ``on_image`` is called
    after each image is read (a progress bar)."""
    check_count(files, files[0].parent if files else Path("."), (gcfg.proj_width, gcfg.proj_height))
    n = n_patterns(gcfg.proj_width, gcfg.proj_height)
    tick = on_image or (lambda: None)
    white, black = read_gray(files[n]), read_gray(files[n + 1])
    tick()
    tick()

    def load(i: int) -> NDArray[np.float32]:
        img = read_gray(files[i])
        if img.shape != white.shape:
            raise BadInputError(f"size {img.shape[1]}x{img.shape[0]} differs from the white image's "
                                f"{white.shape[1]}x{white.shape[0]}", where=files[i])
        tick()
        return img

    return decode_graycode(load, white, black, full_scale, gcfg), (white.shape[1], white.shape[0])


def _node_array(node: Any, key: str, path: Path) -> NDArray[np.float64] | None:
    """A FileStorage node as a float64 array: an ``opencv-matrix``, a (nested) sequence of numbers or a number;
    None when absent."""
    if node.empty() or node.isNone():
        return None
    if node.isSeq():
        return np.array([v for i in range(node.size()) for v in np.ravel(_node_array(node.at(i), key, path))], np.float64)
    if node.isReal() or node.isInt():
        return np.array([node.real()], np.float64)
    if node.isMap():
        try:
            m = node.mat()
        except cv2.error:
            m = None
        if m is not None:
            return np.asarray(m, np.float64)
    raise BadInputError(f"'{key}' is not a matrix or a list of numbers", where=path)


@dataclass(frozen=True)
class CalibrationFile:
    """A stereo calibration as read from its file (intrinsics in the file's pixels, T in metres).

    Attributes:
        K0, dist0, K1, dist1: intrinsics (3, 3) px and distortion (k1, k2, p1, p2[, k3, ...]).
        R: (3, 3), T_m: (3,) metres, ``X1 = R X0 + T``.
        size: the ``image_width`` / ``image_height`` the file states (intrinsics are scaled from it), or None.
        path: the file.
    """

    K0: NDArray[np.float64]
    dist0: NDArray[np.float64]
    K1: NDArray[np.float64]
    dist1: NDArray[np.float64]
    R: NDArray[np.float64]
    T_m: NDArray[np.float64]
    size: tuple[int, int] | None
    path: Path

    def at_sizes(self, sizes: tuple[tuple[int, int], tuple[int, int]]) -> StereoCalibration:
        """The calibration for images of these (W, H) (intrinsics scaled when the file states another size)."""
        cams = []
        for K, dist, size in ((self.K0, self.dist0, sizes[0]), (self.K1, self.dist1, sizes[1])):
            cam = CameraCalibration(K, dist, self.size or size)
            if self.size and tuple(self.size) != tuple(size):
                cam = cam.scaled(size[0] / self.size[0], size[1] / self.size[1])
            cams.append(cam)
        st = StereoCalibration(cams[0], cams[1], self.R, self.T_m, float("nan"))
        st.rectify()
        return st


def read_calibration(path: Path, units: str) -> CalibrationFile:
    """K0, dist0, K1, dist1, R, T from an OpenCV FileStorage file (YAML or XML; T in ``units``), checked: a garbage
    file, a missing or malformed key, an R that is not a rotation, intrinsics that are not a camera matrix, and a
    baseline outside :data:`BASELINE_RANGE_M` (T in the wrong units) are each a one-line :class:`BadInputError`."""
    if units not in UNITS_M:
        raise BadInputError(f"--units must be mm or m, got {units!r}")
    if not path.is_file():
        raise BadInputError("calibration file not found", where=path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # keep fs alive while reading nodes
        opened = fs.isOpened()
    except (cv2.error, SystemError) as exc:  # OpenCV 5's binding raises SystemError on unparsable text
        msg = getattr(exc, "msg", "") or "unparsable"
        raise BadInputError(f"not an OpenCV FileStorage file (YAML or XML: {msg.strip()})", where=path) from exc
    if not opened:
        raise BadInputError("not an OpenCV FileStorage file (YAML or XML)", where=path)
    try:
        m: dict[str, NDArray[np.float64]] = {}
        for key, n in (("K0", 9), ("dist0", None), ("K1", 9), ("dist1", None), ("R", 9), ("T", 3)):
            v = _node_array(fs.getNode(key), key, path)
            if v is None:
                raise BadInputError(f"lacks '{key}' (needs K0, dist0, K1, dist1, R, T)", where=path)
            if (n is not None and v.size != n) or (n is None and v.size not in (4, 5, 8, 12, 14)):
                want = n if n is not None else "4, 5, 8, 12 or 14"
                raise BadInputError(f"'{key}' has {v.size} values, expected {want}", where=path)
            if not np.isfinite(v).all():
                raise BadInputError(f"'{key}' holds values that are not finite", where=path)
            m[key] = v.reshape(3, 3) if n == 9 else v.ravel()
        w, h = (_node_array(fs.getNode(k), k, path) for k in ("image_width", "image_height"))
    finally:
        fs.release()
    size = (int(w[0]), int(h[0])) if w is not None and h is not None else None
    if not np.allclose(m["R"] @ m["R"].T, np.eye(3), atol=1e-4) or np.linalg.det(m["R"]) < 0:
        raise BadInputError("'R' is not a rotation matrix", where=path)
    for k in ("K0", "K1"):
        K = m[k]
        if not (K[0, 0] > 0 and K[1, 1] > 0 and np.allclose(K[2], [0, 0, 1]) and K[1, 0] == 0):
            raise BadInputError(f"'{k}' is not a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0",
                                where=path)
    T_m = m["T"] * UNITS_M[units]
    check_baseline(float(np.linalg.norm(T_m)), units, path)
    return CalibrationFile(m["K0"], m["dist0"], m["K1"], m["dist1"], m["R"], T_m, size, path)


def _units_hint(factor: float, units: str) -> str:
    """What --units would fix a length that is ``factor`` times too large."""
    if units == "mm" and factor < 1:
        return "T looks like metres: use --units m"
    if units == "m" and factor > 1:
        return "T looks like millimetres: use --units mm (the default)"
    return "check the units of T (--units) and the calibration"


def check_baseline(baseline_m: float, units: str, where: Path) -> None:
    """Refuse a baseline outside :data:`BASELINE_RANGE_M`, naming the likely cause (T's units)."""
    lo, hi = BASELINE_RANGE_M
    if not lo <= baseline_m <= hi:
        raise BadInputError(f"the baseline |T| = {baseline_m * 1000:.4g} mm (T read in {units}) is implausible for a "
                            f"stereo or camera-projector rig ({lo * 1000:g} mm .. {hi:g} m): "
                            f"{_units_hint(baseline_m / lo if baseline_m < lo else baseline_m / hi, units)}", where=where)


def check_scene_depth(median_depth_m: float, baseline_m: float, units: str, where: Path) -> None:
    """Refuse a scene whose median triangulated depth is implausible, in metres (:data:`SCENE_DEPTH_RANGE_M`: T's
    units) or against the baseline (:data:`DEPTH_PER_BASELINE`: a calibration of another rig)."""
    lo, hi = SCENE_DEPTH_RANGE_M
    if not median_depth_m > 0:
        raise BadInputError("the matched points triangulate behind camera 0: cam0 and cam1 are swapped, or R, T take "
                            "camera 1 to camera 0 (expected X1 = R X0 + T)", where=where)
    if not lo <= median_depth_m <= hi:
        factor = median_depth_m / lo if median_depth_m < lo else median_depth_m / hi
        raise BadInputError(f"with the baseline |T| = {baseline_m * 1000:.4g} mm the scene's median depth is "
                            f"{median_depth_m * 1000:.4g} mm, implausible for a projector-lit scene ({lo * 1000:g} mm .. "
                            f"{hi:g} m): {_units_hint(factor, units)}", where=where)
    r = median_depth_m / baseline_m
    rlo, rhi = DEPTH_PER_BASELINE
    if not rlo <= r <= rhi:
        raise BadInputError(f"the scene's median depth is {r:.3g} x the baseline ({median_depth_m:.4g} m against "
                            f"{baseline_m:.4g} m; plausible {rlo:g} .. {rhi:g}): the calibration does not belong to "
                            f"these images (another rig? cameras swapped?)", where=where)
