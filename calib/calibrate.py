"""Per-camera and stereo calibration from ChArUco detections, rectification, FileStorage YAML.

Conventions: ``X_cam1 = R @ X_cam0 + T`` (OpenCV ``stereoCalibrate``), translations in metres (the board is in
metres), pixel coordinates with the centre of the top-left pixel at (0, 0).

Intrinsics per focus setting (measured in ``tests/process/test_calib.py``): from only three ChArUco pairs,
re-estimating intrinsics makes the rotation about ten times worse than holding them fixed, so
:func:`stereo_calibrate` re-estimates only R, T (``CALIB_FIX_INTRINSIC``) by default; intrinsics come from a prior
per-camera calibration (many views, :func:`calibrate_camera`) or the manifest's rig table.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.errors import BadInputError, CalibrationError
from dp5k_common.io import atomic_path

from .detect import CharucoDetection


@dataclass(frozen=True)
class CalibConfig:
    """Acceptance bounds and options.

    Attributes:
        min_corners: fewest ChArUco corners a view (or a pair's common corners) must have to be used.
        min_views: fewest usable views (pairs for stereo).
        max_rms_px: largest acceptable RMS reprojection error, pixels.
        fix_k3: hold k3 = 0 in ``calibrateCamera`` (few views cannot determine it).
    """

    min_corners: int = 12
    min_views: int = 3
    max_rms_px: float = 1.0
    fix_k3: bool = True


@dataclass
class CameraCalibration:
    """Pinhole intrinsics with OpenCV distortion.

    Attributes:
        K: (3, 3) camera matrix, pixels.
        dist: (5,) distortion (k1, k2, p1, p2, k3).
        image_size: (W, H) pixels.
        rms_px: RMS reprojection error of the calibration (NaN when given, not estimated).
    """

    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    image_size: tuple[int, int]
    rms_px: float = float("nan")
    n_views: int = 0

    def scaled(self, sx: float, sy: float) -> CameraCalibration:
        """Intrinsics for an image resampled by (sx, sy) (pixel centres mapped x' = (x + 0.5) sx - 0.5)."""
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        size = (int(round(self.image_size[0] * sx)), int(round(self.image_size[1] * sy)))
        return CameraCalibration(K, self.dist.copy(), size, self.rms_px, self.n_views)


@dataclass
class StereoCalibration:
    """A calibrated stereo pair with its rectification.

    Attributes:
        cam0, cam1: intrinsics.
        R: (3, 3), T: (3,) metres, ``X_cam1 = R X_cam0 + T``.
        rms_px: RMS reprojection error of ``stereoCalibrate``.
        R0, R1, P0, P1, Q: ``stereoRectify`` outputs (CALIB_ZERO_DISPARITY, alpha=0).
        per_view_rms_px: (n, 2) per-view errors.
    """

    cam0: CameraCalibration
    cam1: CameraCalibration
    R: NDArray[np.float64]
    T: NDArray[np.float64]
    rms_px: float
    R0: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    R1: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    P0: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 4)))
    P1: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 4)))
    Q: NDArray[np.float64] = field(default_factory=lambda: np.zeros((4, 4)))
    n_pairs: int = 0
    fixed_intrinsics: bool = True

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T))

    def rectify(self) -> None:
        """Fill R0, R1, P0, P1, Q with ``cv2.stereoRectify(CALIB_ZERO_DISPARITY, alpha=0)``."""
        self.R0, self.R1, self.P0, self.P1, self.Q, _, _ = cv2.stereoRectify(
            self.cam0.K, self.cam0.dist, self.cam1.K, self.cam1.dist, self.cam0.image_size, self.R, self.T.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)

    def save_yaml(self, path: str | os.PathLike[str]) -> None:
        """Write OpenCV FileStorage YAML (atomically)."""
        with atomic_path(path, suffix=".yaml") as tmp:
            fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
            try:
                fs.write("image_width", int(self.cam0.image_size[0]))
                fs.write("image_height", int(self.cam0.image_size[1]))
                for name in ("K0", "dist0", "K1", "dist1", "R", "T", "R0", "R1", "P0", "P1", "Q"):
                    fs.write(name, np.asarray(self._get(name), dtype=np.float64))
                fs.write("rms_px", float(self.rms_px))
                fs.write("rms0_px", float(self.cam0.rms_px))
                fs.write("rms1_px", float(self.cam1.rms_px))
                fs.write("n_pairs", int(self.n_pairs))
                fs.write("fixed_intrinsics", int(self.fixed_intrinsics))
            finally:
                fs.release()

    def _get(self, name: str) -> NDArray[np.float64]:
        table = {"K0": self.cam0.K, "dist0": self.cam0.dist, "K1": self.cam1.K, "dist1": self.cam1.dist}
        return table[name] if name in table else getattr(self, name)

    @classmethod
    def load_yaml(cls, path: str | os.PathLike[str]) -> StereoCalibration:
        """Read a file written by :meth:`save_yaml`."""
        if not Path(path).is_file():
            raise BadInputError("calibration file not found", where=path)
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # keep fs alive while reading nodes
        try:
            m = {n: fs.getNode(n).mat() for n in ("K0", "dist0", "K1", "dist1", "R", "T", "R0", "R1", "P0", "P1", "Q")}
            if any(v is None for v in m.values()):
                raise BadInputError("calibration YAML lacks a matrix", where=path)
            size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
            rms = fs.getNode("rms_px").real()
            c0 = CameraCalibration(m["K0"], m["dist0"].ravel(), size, fs.getNode("rms0_px").real())
            c1 = CameraCalibration(m["K1"], m["dist1"].ravel(), size, fs.getNode("rms1_px").real())
            return cls(c0, c1, m["R"], m["T"].ravel(), rms, m["R0"], m["R1"], m["P0"], m["P1"], m["Q"],
                       int(fs.getNode("n_pairs").real()), bool(int(fs.getNode("fixed_intrinsics").real())))
        finally:
            fs.release()


def _usable(dets: Sequence[CharucoDetection | None], cfg: CalibConfig) -> list[CharucoDetection]:
    return [d for d in dets if d is not None and len(d) >= cfg.min_corners]


def calibrate_camera(
    detections: Sequence[CharucoDetection | None], image_size: tuple[int, int], cfg: CalibConfig = CalibConfig(),
    where: str = "calibration",
) -> CameraCalibration:
    """Intrinsics from several ChArUco views (``cv2.calibrateCamera``).

    Raises:
        CalibrationError: fewer than ``min_views`` views with ``min_corners`` corners, or RMS above ``max_rms_px``.
    """
    dets = _usable(detections, cfg)
    if len(dets) < cfg.min_views:
        raise CalibrationError(
            f"only {len(dets)} of {len(detections)} views have >= {cfg.min_corners} ChArUco corners "
            f"(need {cfg.min_views})", where=where)
    flags = cv2.CALIB_FIX_K3 if cfg.fix_k3 else 0
    rms, K, dist, _r, _t = cv2.calibrateCamera(
        [d.board_m for d in dets], [d.image_px for d in dets], tuple(image_size), None, None, flags=flags)
    if not np.isfinite(rms) or rms > cfg.max_rms_px:
        raise CalibrationError(f"reprojection error {rms:.3f} px exceeds the bound {cfg.max_rms_px} px", where=where)
    return CameraCalibration(K, dist.ravel()[:5], tuple(image_size), float(rms), len(dets))


def stereo_calibrate(
    pairs: Sequence[tuple[CharucoDetection | None, CharucoDetection | None]],
    cam0: CameraCalibration,
    cam1: CameraCalibration,
    cfg: CalibConfig = CalibConfig(),
    fix_intrinsics: bool = True,
    where: str = "stereo calibration",
) -> StereoCalibration:
    """R, T between two cameras from ChArUco pairs (corners seen in both views), then ``stereoRectify``.

    Args:
        pairs: (detection in cam0, detection in cam1) per board pose; None = not found.
        cam0, cam1: intrinsics (held fixed when ``fix_intrinsics``; otherwise used as the initial guess).
        fix_intrinsics: ``CALIB_FIX_INTRINSIC`` (default: three pairs cannot pin intrinsics down).

    Raises:
        CalibrationError: too few usable pairs/common corners, or RMS above ``max_rms_px``.
    """
    obj, p0, p1 = [], [], []
    for d0, d1 in pairs:
        if d0 is None or d1 is None:
            continue
        common = np.intersect1d(d0.ids, d1.ids)
        if len(common) < cfg.min_corners:
            continue
        a, b = d0.subset(common), d1.subset(common)
        obj.append(a.board_m)
        p0.append(a.image_px)
        p1.append(b.image_px)
    if len(obj) < cfg.min_views:
        raise CalibrationError(
            f"only {len(obj)} of {len(pairs)} ChArUco pairs share >= {cfg.min_corners} corners "
            f"(need {cfg.min_views})", where=where)
    flags = cv2.CALIB_FIX_INTRINSIC if fix_intrinsics else (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    rms, K0, d0_, K1, d1_, R, T, _E, _F = cv2.stereoCalibrate(
        obj, p0, p1, cam0.K.copy(), cam0.dist.copy(), cam1.K.copy(), cam1.dist.copy(), tuple(cam0.image_size),
        flags=flags, criteria=crit)
    if not np.isfinite(rms) or rms > cfg.max_rms_px:
        raise CalibrationError(f"stereo reprojection error {rms:.3f} px exceeds the bound {cfg.max_rms_px} px",
                               where=where)
    c0 = CameraCalibration(K0, d0_.ravel()[:5], cam0.image_size, cam0.rms_px, cam0.n_views)
    c1 = CameraCalibration(K1, d1_.ravel()[:5], cam1.image_size, cam1.rms_px, cam1.n_views)
    st = StereoCalibration(c0, c1, np.asarray(R, np.float64), np.asarray(T, np.float64).ravel(), float(rms),
                           n_pairs=len(obj), fixed_intrinsics=fix_intrinsics)
    st.rectify()
    return st


def rotation_angle_deg(Ra: NDArray[np.float64], Rb: NDArray[np.float64]) -> float:
    """Angle of the rotation ``Ra^T Rb`` in degrees."""
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def rectify_images(st: StereoCalibration, img0: NDArray, img1: NDArray) -> tuple[NDArray, NDArray]:
    """Rectify a stereo pair with ``initUndistortRectifyMap`` + ``remap(INTER_LINEAR)``."""
    out = []
    for cam, Rr, P, img in ((st.cam0, st.R0, st.P0, img0), (st.cam1, st.R1, st.P1, img1)):
        mx, my = cv2.initUndistortRectifyMap(cam.K, cam.dist, Rr, P, cam.image_size, cv2.CV_32FC1)
        out.append(cv2.remap(img, mx, my, cv2.INTER_LINEAR))
    return out[0], out[1]
