"""``dp5k sl-depth``'s extrinsics refinement against OpenCV's own self-calibration, on a real capture (prints a table).

The reference does not use dp5k's refinement at all: the same decoded camera-camera matches (the Gray code gives
them without any calibration), undistorted with the calibration file's intrinsics, go to OpenCV's essential
matrix (``cv2.findEssentialMat``, RANSAC at 0.5 px on the undistorted points) and ``cv2.recoverPose``; the baseline
length is the file's ``|T|`` (epipolar geometry has no scale); the matches are triangulated with
``cv2.triangulatePoints`` and their z in camera 0 is the reference depth. dp5k's depth (``depth_m.tif`` written by
``dp5k sl-depth``) is compared with it at the matched camera-0 pixels where both have depth: the median of
|dp5k - reference| / reference and of the signed difference.

    .venv/bin/python benchmarks/sl_refine_reference.py IMAGES CALIBRATION OUT --projector WxH [--units mm]

OUT must hold a finished ``dp5k sl-depth IMAGES CALIBRATION OUT`` (the script runs it when OUT has no report).
The GSoC 2015 statue captures (RobertaRavanelli/GSoC2015_statue_dataset, no licence: used locally, not committed)
are what docs/processing.md records: their ``pattern_cam2`` images are the calibration's first camera.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from dp5k_process.refine import Matches, sl_matches
from dp5k_process.sl_depth import decode_folder, decoder_config, full_scale_of, list_images, read_stereo_yaml, sl_depth
from dp5k_process.triangulate import TriangulationConfig
from run_info import recording


def reference_depth(m: Matches, K0: np.ndarray, d0: np.ndarray, K1: np.ndarray, d1: np.ndarray, baseline_m: float,
                    n_fit: int = 50000, seed: int = 0) -> tuple[np.ndarray, dict[str, float]]:
    """z (metres) in camera 0 of every match, from OpenCV's essential matrix of the matches and ``baseline_m``."""
    n0 = cv2.undistortPoints(m.x0.reshape(-1, 1, 2), K0, d0).reshape(-1, 2)
    n1 = cv2.undistortPoints(m.x1.reshape(-1, 1, 2), K1, d1).reshape(-1, 2)
    f_px = 0.5 * float(K0[0, 0] + K1[0, 0])
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(n0), min(n_fit, len(n0)), replace=False)
    cv2.setRNGSeed(seed)
    E, inl = cv2.findEssentialMat(n0[idx], n1[idx], np.eye(3), method=cv2.RANSAC, prob=0.9999, threshold=0.5 / f_px)
    _, R, t, _ = cv2.recoverPose(E, n0[idx], n1[idx], np.eye(3), mask=inl.copy())
    T = t.ravel() * baseline_m
    P0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = np.hstack([R, T[:, None]])
    X = cv2.triangulatePoints(P0, P1, n0.T.astype(np.float64), n1.T.astype(np.float64))
    z = X[2] / X[3]
    info = {"ransac_inliers": float(inl.sum()) / len(idx),
            "rotation_vector_deg": np.degrees(cv2.Rodrigues(R)[0].ravel()).round(4).tolist(),
            "T_m": T.round(5).tolist()}
    return z, info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("images", type=Path)
    ap.add_argument("calibration", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--projector", required=True)
    ap.add_argument("--units", default="mm")
    a = ap.parse_args()
    proj = tuple(int(v) for v in a.projector.lower().split("x"))
    if not (a.out / "report.json").is_file():
        sl_depth(a.images, a.calibration, a.out, proj, a.units)  # type: ignore[arg-type]
    rep = json.loads((a.out / "report.json").read_text())
    files = {cam: list_images(a.images / cam) for cam in ("cam0", "cam1")}
    fs = full_scale_of(files["cam0"][0], None)
    gcfg = decoder_config("auto", proj, fs)  # type: ignore[arg-type]
    decs, sizes = {}, {}
    for cam in ("cam0", "cam1"):
        decs[cam], sizes[cam] = decode_folder(files[cam], gcfg, fs)
    st = read_stereo_yaml(a.calibration, a.units, (sizes["cam0"], sizes["cam1"]))
    m = sl_matches(decs, TriangulationConfig())
    z_ref, info = reference_depth(m, st.cam0.K, st.cam0.dist, st.cam1.K, st.cam1.dist, float(np.linalg.norm(st.T)))
    spread = max(float(np.nanmedian(np.abs(z / z_ref - 1))) for z, _ in
                 (reference_depth(m, st.cam0.K, st.cam0.dist, st.cam1.K, st.cam1.dist, float(np.linalg.norm(st.T)),
                                  seed=k) for k in (1, 2)))
    depth = cv2.imread(str(a.out / "depth_m.tif"), cv2.IMREAD_UNCHANGED)
    xi, yi = m.x0[:, 0].astype(int), m.x0[:, 1].astype(int)
    ours = depth[yi, xi]
    ok = np.isfinite(ours) & np.isfinite(z_ref) & (z_ref > 0)
    rel = (ours[ok] - z_ref[ok]) / z_ref[ok]
    ref = rep["refinement"]
    n0 = cv2.undistortPoints(m.x0[ok].reshape(-1, 1, 2), st.cam0.K, st.cam0.dist).reshape(-1, 2).T
    n1 = cv2.undistortPoints(m.x1[ok].reshape(-1, 1, 2), st.cam1.K, st.cam1.dist).reshape(-1, 2).T

    def pose_vs_reference(pose: dict | None) -> str:
        """Median |z - reference| / reference of the same matches triangulated with a pose of the report."""
        if not pose:
            return "-"
        P1 = np.hstack([np.array(pose["R"]), np.array(pose["T_m"])[:, None]])
        X = cv2.triangulatePoints(np.hstack([np.eye(3), np.zeros((3, 1))]), P1, n0, n1)
        d = (X[2] / X[3] - z_ref[ok]) / z_ref[ok]
        return f"{100 * np.median(np.abs(d)):.2f} % (signed {100 * np.median(d):+.2f} %)"

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip()
    five, three = ref.get("five_parameters") or {}, ref.get("three_parameters") or {}
    print(f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC, commit {commit}, load {os.getloadavg()[0]:.1f}")
    print(f"\n| {a.images.name} | value |\n|---|---|")
    rows = [("matches (probe scale), compared (both have depth)", f"{len(m.x0)}, {int(ok.sum())}"),
            ("used", ref.get("mode", "not refined") if ref.get("applied") else "the given calibration"),
            ("given calibration: epipolar median / p90 (px); vs reference",
             f"{ref['epipolar_error_px_given']:.2f} / {ref['epipolar_p90_px_given']:.2f}; {pose_vs_reference(ref.get('charuco'))}"),
            ("three parameters: epipolar median / p90 (px); vs reference",
             f"{three.get('epipolar_error_px', float('nan')):.2f} / {three.get('epipolar_p90_px', float('nan')):.2f}; "
             f"{pose_vs_reference(three)}"),
            ("five parameters: epipolar median / p90 (px); vs reference",
             f"{five.get('epipolar_error_px', float('nan')):.2f} / {five.get('epipolar_p90_px', float('nan')):.2f}; "
             f"{pose_vs_reference(five)}"),
            ("five parameters: depth-scale sd from the fit, flatness",
             f"{five.get('depth_sd_pct', float('nan')):.3f} %, {five.get('flatness', float('nan')):.3f}"),
            ("OpenCV reference: rotation vector (deg), T (m), RANSAC inliers",
             f"{info['rotation_vector_deg']}, {info['T_m']}, {100 * info['ransac_inliers']:.1f} %"),
            ("the reference's own spread (RANSAC seeds 1, 2 against 0: largest median abs. rel. difference)",
             f"{100 * spread:.2f} %"),
            ("dp5k depth_m.tif vs reference: median abs. rel. difference (p90)",
             f"**{100 * np.median(np.abs(rel)):.2f} %** ({100 * np.percentile(np.abs(rel), 90):.2f} %)"),
            ("median signed difference", f"{100 * np.median(rel):+.2f} %"),
            ("dp5k depth coverage of camera 0", f"{100 * rep['depth_coverage']:.1f} %")]
    for k, v in rows:
        print(f"| {k} | {v} |")


if __name__ == "__main__":
    with recording(f"process-sl-refine-{Path(sys.argv[1]).name if len(sys.argv) > 1 else 'run'}",
                   "sl-depth's refinement against OpenCV's self-calibration on a real capture"):
        main()
