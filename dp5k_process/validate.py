"""``dp5k validate-depth``: structured-light depth accuracy on a wall (paper section 3.5, Eq. 4).

.. math:: \\text{relative err} = \\frac{\\operatorname{mean}(\\text{PtP})}{\\operatorname{mean}(D_{esti})}

The plane ``g`` comes from the ChArUco board on the wall alone (``solvePnP`` of the detected corners with the
camera's own K, dist): normal ``n = R[:, 2]``, point ``p0 = t``. The structured-light points are those of the
camera's depth map near detected corners (discs of one square around each, so a hidden part of the board, or
whatever hides it, is left out); PtP = ``|(X - p0) . n|``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.detect import CharucoDetection, detect_charuco
from dp5k_common.errors import CalibrationError, StageError
from dp5k_common.io import write_bytes_atomic, write_json_atomic
from dp5k_common.software import provenance

from .filters import backproject
from .graycode import GrayCodeConfig
from .pipeline import ProcessConfig, calibrate_session, decode_camera, depth_for_camera, raw_gray, read_main
from .session import load_session
from .triangulate import normalised_rays


def board_plane(det: CharucoDetection, K: NDArray[np.float64], dist: NDArray[np.float64]
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Plane of the board in camera coordinates from PnP: (unit normal n, point p0 in metres, rms px)."""
    if len(det) < 6:
        raise CalibrationError(f"only {len(det)} ChArUco corners on the wall board (need 6)")
    ok, rvec, tvec = cv2.solvePnP(det.board_m.astype(np.float64), det.image_px.astype(np.float64), K, dist,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("solvePnP failed on the wall board")
    proj, _ = cv2.projectPoints(det.board_m.astype(np.float64), rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - det.image_px) ** 2, 1))))
    R = cv2.Rodrigues(rvec)[0]
    return R[:, 2].copy(), tvec.ravel().astype(np.float64), rms


def board_mask(det: CharucoDetection, shape: tuple[int, int], radius_px: float) -> NDArray[np.bool_]:
    """Pixels within ``radius_px`` of a detected corner (the visible part of the board)."""
    m = np.zeros(shape, np.uint8)
    for x, y in det.image_px:
        cv2.circle(m, (int(round(x)), int(round(y))), max(1, int(round(radius_px))), 1, -1)
    return m.astype(bool)


def plane_error(points_m: NDArray[np.float64], n: NDArray[np.float64], p0: NDArray[np.float64]
                ) -> tuple[float, NDArray[np.float64]]:
    """Eq. 4: mean |point-to-plane| / mean depth (z), and the signed residuals (m)."""
    res = (points_m - p0[None, :]) @ n
    return float(np.mean(np.abs(res)) / np.mean(points_m[:, 2])), res


def residual_picture(res_map_mm: NDArray[np.float32], base: NDArray[np.float32], path: Path, scale_mm: float) -> None:
    """PNG: the camera image in gray with signed point-to-plane residuals in colour (blue -, red +)."""
    g = base / max(float(np.percentile(base, 99)), 1e-6)
    gray = (np.clip(g, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    ok = np.isfinite(res_map_mm)
    v = np.clip((np.nan_to_num(res_map_mm) / scale_mm + 1) / 2, 0, 1)
    col = cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_JET)
    img[ok] = col[ok]
    cv2.putText(img, f"PtP residual, full scale +-{scale_mm:.1f} mm", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                (255, 255, 255), 1, cv2.LINE_AA)
    ok_, buf = cv2.imencode(".png", img)
    write_bytes_atomic(path, buf.tobytes())


def validate_depth(capture: str | os.PathLike[str], out: str | os.PathLike[str], cfg: ProcessConfig = ProcessConfig(),
                   camera: str = "cam0") -> dict[str, Any]:
    """Run the depth pipeline on a wall session and compare with the board plane (Eq. 4); writes a report.

    Returns:
        dict with relative_error, n_points, mean_depth_m, mean_ptp_mm, pnp_rms_px, plane normal/point, and the
        arrays ``points_m`` (N, 3), ``residual_m`` (N,) for tests.
    """
    session = load_session(capture)
    cs = session.cameras[camera]
    probe = read_main(session, cs.sl[-1])[0]
    raw_size = (probe.shape[1], probe.shape[0])
    st, cal_info = calibrate_session(session, cfg, raw_size)
    gcfg = cfg.gray or GrayCodeConfig.for_linear_raw(*session.projector_size)
    decs = {c: decode_camera(session, c, gcfg)[0] for c in ("cam0", "cam1")}
    depth, dinfo = depth_for_camera(decs, camera, st, cfg)
    cal = st.cam0 if camera == "cam0" else st.cam1
    sharp = raw_gray(read_main(session, cs.sharp))
    det = detect_charuco(sharp, cfg.board)
    if det is None:
        raise CalibrationError("no ChArUco board found on the wall", where=cs.sharp)
    n, p0, rms = board_plane(det, cal.K, cal.dist)
    d_corner = np.median(np.linalg.norm(np.diff(det.image_px, axis=0), axis=1)) if len(det) > 1 else 5.0
    mask = board_mask(det, depth.shape, 0.8 * d_corner)
    d = np.where(mask, depth, np.nan).astype(np.float32)
    rays = normalised_rays(cal)
    pts, valid = backproject(d, rays)
    if pts.shape[0] < 20:
        raise StageError(f"only {pts.shape[0]} structured-light points on the board", where=session.root)
    rel, res = plane_error(pts, n, p0)
    res_map = np.full(depth.shape, np.nan, np.float32)
    res_map[valid] = res * 1000.0
    outp = Path(out)
    scale = max(1.0, float(np.percentile(np.abs(res), 99)) * 1000.0)
    residual_picture(res_map, sharp, outp / "residuals.png", scale)
    result = {
        "capture": str(capture), "camera": camera, "relative_error": rel, "relative_error_percent": 100 * rel,
        "n_points": int(pts.shape[0]), "mean_depth_m": float(pts[:, 2].mean()),
        "mean_ptp_mm": float(np.mean(np.abs(res)) * 1000), "pnp_rms_px": rms, "board_corners": len(det),
        "plane_normal": n.tolist(), "plane_point_m": p0.tolist(), "calibration": cal_info, "depth": dinfo,
        "reference": {"paper_percent": 0.59, "realsense_d415_percent": 2.0}, "provenance": provenance(),
    }
    write_json_atomic(outp / "report.json", result)
    result["points_m"] = pts
    result["residual_m"] = res
    result["mask"] = valid
    return result
