"""One scene, raw session -> processed pairs (paper sections 3.4-3.7).

Steps (each timed in the scene report):

1. ``calibrate``: ChArUco in the three pairs -> R, T with the intrinsics held fixed (see ``calib/``).
2. ``decode``: Gray code of each camera, on the raw mosaic at full raw resolution (pos/neg comparisons are
   per pixel, so each photosite is compared with itself and no demosaic is needed).
3. ``depth``: per projector scale 1, 1/2, 1/4, 1/8: match through the projector code, triangulate, filter;
   then Eq. 3; in each DP camera's own pixel grid.
4. ``views``: sharp / left / right from the Dual Pixel RAWs (half-size demosaic, white balance, linear).
5. ``pairs``: resize to the output size, Eq. 5 focus distance, Eq. 7 / lens focal length, Eq. 6 CoC.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calib.board import DEFAULT_BOARD, BoardSpec
from calib.calibrate import (CalibConfig, CameraCalibration, StereoCalibration, calibrate_camera,
                             stereo_calibrate)
from calib.detect import detect_charuco
from dp5k_common.dataset import Pair, PairParams
from dp5k_common.errors import BadInputError, StageError
from dp5k_common.optics import coc_diameter_px, thin_lens_focal_length_mm
from dp5k_common.rawfile import DualPixelFrames, read_dual_pixel, read_frame

from .filters import FilterConfig, filter_depth, recursive_fill
from .focus import FocusConfig, focus_distance
from .graycode import GrayCodeConfig, GrayDecode, decode_graycode
from .projector import ProjectorCalibConfig, calibrate_projector, correspondence_subset, mixed_codes, procam_depth
from .rawimage import dp_views, resize_image
from .refine import RefineConfig, ViewCache, cached_centroids, cached_view, refine_stereo
from .session import Session, check_size
from .triangulate import (CodeView, TriangulationConfig, camera_px_per_projector_px, depth_from_match, match_in_other,
                          normalised_rays)


@dataclass(frozen=True)
class ProcessConfig:
    """Settings of ``dp5k process``.

    Attributes:
        out_size: (W, H) of the output; None = half the raw size (the half-size demosaic).
        gray: decoder settings; None = :meth:`GrayCodeConfig.for_linear_raw` at the session's projector size.
        tri, filt: matching and filter settings.
        projector: self-calibration of the projector from the stereo points, for camera-projector depth where
            the other camera cannot see (``dp5k_process.projector``); None = stereo depth only.
        focus_window_px: Eq. 5 window (w, h) in pixels of a ``focus_window_ref_width``-wide image (paper 30 x 20
            at 1680; the released code uses 60 x 40); scaled with the output width, at least 3 x 3.
        calib: calibration acceptance bounds.
        intrinsics: FileStorage YAML with K0, dist0, K1, dist1 at raw resolution (a prior per-camera
            calibration); None = the manifest's, else estimated from the session's own ChArUco views.
        board: the ChArUco board.
        refine: checking the ChArUco extrinsics against the structured-light matches, refining them when the
            ray-gap test rejects most (``dp5k_process.refine``); None = never.
    """

    out_size: tuple[int, int] | None = None
    gray: GrayCodeConfig | None = None
    tri: TriangulationConfig = TriangulationConfig()
    filt: FilterConfig = FilterConfig()
    projector: ProjectorCalibConfig | None = ProjectorCalibConfig()
    focus_window_px: tuple[int, int] = (30, 20)
    focus_window_ref_width: int = 1680
    calib: CalibConfig = CalibConfig()
    intrinsics: str | None = None
    board: BoardSpec = DEFAULT_BOARD
    refine: RefineConfig | None = RefineConfig()


@dataclass
class SceneResult:
    """Everything ``process_scene`` made: the pairs, the calibration and the report numbers."""

    scene: str
    pairs: list[Pair]
    calibration: StereoCalibration
    report: dict[str, Any] = field(default_factory=dict)
    depth_m: dict[str, NDArray[np.float32]] = field(default_factory=dict)


def read_frames(session: Session, path: Path) -> DualPixelFrames:
    """Read a Dual Pixel RAW of the session (size checked against the manifest first)."""
    check_size(session, path)
    return read_dual_pixel(path)


def read_main(session: Session, path: Path) -> tuple[NDArray[np.uint16], int, int]:
    """Frame 0 (main) of a raw file of the session, size checked: (mosaic, black, white)."""
    check_size(session, path)
    return read_frame(path, 0)


def raw_gray(frames: DualPixelFrames | tuple[NDArray[np.uint16], int, int]) -> NDArray[np.float32]:
    """Full-resolution gray image of the main frame (Bayer -> gray), raw counts above black."""
    main, black = (frames.main, frames.black_level) if isinstance(frames, DualPixelFrames) else frames[:2]
    m = np.clip(main.astype(np.int32) - black, 0, 65535).astype(np.uint16)
    return cv2.cvtColor(m, cv2.COLOR_BayerRG2GRAY).astype(np.float32)


def load_intrinsics(path: str | Path) -> tuple[CameraCalibration, CameraCalibration]:
    """A prior per-camera calibration (FileStorage YAML with K0, dist0, K1, dist1, image_width/height)."""
    st = StereoCalibration.load_yaml(path)
    return st.cam0, st.cam1


def calibrate_session(session: Session, cfg: ProcessConfig, raw_size: tuple[int, int]) -> tuple[StereoCalibration, dict[str, Any]]:
    """Stereo calibration of this focus setting from its three ChArUco pairs.

    Intrinsics: ``cfg.intrinsics`` file, else the manifest's per-body K/dist, else estimated from the three views
    of each camera (flagged in the report: three views determine intrinsics poorly). R, T are always re-estimated
    with the intrinsics held fixed.
    """
    c0, c1 = session.cameras["cam0"], session.cameras["cam1"]
    dets = []
    for p0, p1 in zip(c0.charuco, c1.charuco):
        d0 = detect_charuco(raw_gray(read_main(session, p0)), cfg.board)
        d1 = detect_charuco(raw_gray(read_main(session, p1)), cfg.board)
        dets.append((d0, d1))
    info: dict[str, Any] = {"charuco_corners": [[0 if a is None else len(a), 0 if b is None else len(b)] for a, b in dets]}
    if cfg.intrinsics:
        k0, k1 = load_intrinsics(cfg.intrinsics)
        info["intrinsics_from"] = str(cfg.intrinsics)
    elif c0.K is not None and c1.K is not None:
        z = np.zeros(5)
        k0 = CameraCalibration(c0.K, z if c0.dist is None else c0.dist, raw_size)
        k1 = CameraCalibration(c1.K, z if c1.dist is None else c1.dist, raw_size)
        info["intrinsics_from"] = "manifest"
    else:
        ccfg = CalibConfig(cfg.calib.min_corners, 3, cfg.calib.max_rms_px, True)
        k0 = calibrate_camera([d[0] for d in dets], raw_size, ccfg, where=f"{session.scene}/cam0 charuco")
        k1 = calibrate_camera([d[1] for d in dets], raw_size, ccfg, where=f"{session.scene}/cam1 charuco")
        info["intrinsics_from"] = "charuco views of this session (3 per camera)"
    if k0.image_size != raw_size:
        sx, sy = raw_size[0] / k0.image_size[0], raw_size[1] / k0.image_size[1]
        k0, k1 = k0.scaled(sx, sy), k1.scaled(sx, sy)
    st = stereo_calibrate(dets, k0, k1, cfg.calib, fix_intrinsics=True, where=f"{session.scene} stereo calibration")
    info["reprojection_error_px"] = st.rms_px
    info["baseline_m"] = st.baseline_m
    return st, info


def decode_camera(session: Session, cam: str, gcfg: GrayCodeConfig) -> tuple[GrayDecode, tuple[int, int], int]:
    """Decode one camera's structured-light set from the raw mosaics (streamed file by file).

    Returns: the decode, the raw size (W, H) and the white-black range in counts.
    """
    files = session.cameras[cam].sl
    n = len(files) - 2
    white, black_level, white_level = read_main(session, files[n])
    black = read_main(session, files[n + 1])[0]
    shape = white.shape
    full = white_level - black_level

    def load(i: int) -> NDArray[np.uint16]:  # raw counts; the decoder subtracts each pair in float32
        main = read_main(session, files[i])[0]
        if main.shape != shape:
            raise BadInputError(f"raw size {main.shape} differs from the session's {shape}", where=files[i])
        return main

    dec = decode_graycode(load, white.astype(np.float32), black.astype(np.float32), float(full), gcfg)
    return dec, (shape[1], shape[0]), full


def fill_steps_for(view0: CodeView, fill_steps: int, n_scales: int) -> int:
    """Steps of Eq. 3 for this camera: ``fill_steps`` (paper: 3, scales 1, 1/2, 1/4), plus one coarser scale for
    each of those scales whose projector pixel is smaller than a camera pixel, up to ``n_scales``.

    The paper's scales are for its 1680 x 1120 output (3360 px raw): with the studio's 85 mm lenses and the
    projector's 1.5 throw ratio a projector pixel spans ~2.8 raw pixels, so every scale's stripes are resolved.
    On a camera ten times coarser (the small studio scale, ~0.28) the scale-1 to 1/4 stripes are all sub-pixel
    and the last step reaches 1/8 (``view0``: the camera's codes at scale 1)."""
    fp = camera_px_per_projector_px(view0)
    extra = sum(1 for s in range(fill_steps) if np.isfinite(fp) and fp * (1 << s) < 1.0)
    return int(min(n_scales, fill_steps + extra))


def projector_correspondences(views: list[CodeView], depths: list[NDArray[np.float32]], rays: NDArray[np.float32],
                               cfg: ProjectorCalibConfig) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The stereo points (N, 3) metres and their full-scale projector pixels (N, 2) that
    :func:`~.projector.calibrate_projector` fits, from every scale's filtered depth.

    :func:`~.projector.calibrate_projector` keeps the finite correspondences of all scales (scale by scale, each
    row-major: those of ``backproject`` with their ``to_full`` codes) and then a seeded subset of them
    (:func:`~.projector.correspondence_subset`). The same subset is drawn here from their count alone and only its
    points are built, so that fit sees the same correspondences in the same order (``calibrate_projector`` does
    not subsample again: it gets at most ``max_points``), without the points of every valid pixel (20 M at
    paper size)."""
    rays_ok = np.isfinite(rays).all(-1)
    idx = []
    for v, d in zip(views, depths):  # finite point (z and ray) and finite projector pixel (u, v)
        idx.append(np.flatnonzero(np.isfinite(d) & rays_ok & np.isfinite(v.u) & np.isfinite(v.v)))
    counts = np.array([len(i) for i in idx])
    sub = correspondence_subset(int(counts.sum()), cfg)
    starts = np.r_[0, np.cumsum(counts)]
    pts, codes = [], []
    for k, (v, d) in enumerate(zip(views, depths)):
        sel = idx[k] if sub is None else idx[k][sub[(sub >= starts[k]) & (sub < starts[k + 1])] - starts[k]]
        z = d.reshape(-1)[sel].astype(np.float64)
        r = rays.reshape(-1, 2)[sel].astype(np.float64)
        pts.append(np.column_stack([r[:, 0] * z, r[:, 1] * z, z]))
        codes.append(np.column_stack([v.to_full(v.u.reshape(-1)[sel]), v.to_full(v.v.reshape(-1)[sel])]))
    X, x = np.concatenate(pts), np.concatenate(codes).astype(np.float64)
    if sub is not None:  # back into the subset's (random) order
        order = np.concatenate([np.flatnonzero((sub >= starts[k]) & (sub < starts[k + 1])) for k in range(len(idx))])
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        X, x = X[inv], x[inv]
    return X, x


def depth_for_camera(
    decs: dict[str, GrayDecode], ref: str, st: StereoCalibration, cfg: ProcessConfig,
    views_cache: ViewCache | None = None,
) -> tuple[NDArray[np.float32], dict[str, Any]]:
    """Depth (metres, NaN invalid) on ``ref``'s raw pixel grid: per scale match + triangulate + filter, then Eq. 3.

    Pixels the other camera cannot match (hidden from it by a nearer object, or outside its view) are
    triangulated against the projector, calibrated from this camera's stereo points (``cfg.projector``).

    ``views_cache`` (camera, scale) -> code view: pass the same dict to both cameras' calls and each camera's
    views are computed once (a camera's views serve as reference for its own depth and as the other camera
    for its partner's); it holds up to (scales used + 1) views per camera, each about 40 bytes per raw pixel.
    """
    cache: ViewCache = {} if views_cache is None else views_cache

    def view(cam: str, s: int) -> CodeView:
        return cached_view(decs, cam, s, cfg.tri, cache)

    other = "cam1" if ref == "cam0" else "cam0"
    cal = {"cam0": st.cam0, "cam1": st.cam1}
    if ref == "cam0":
        R, T = st.R, st.T
    else:
        R, T = st.R.T, -st.R.T @ st.T
    rays = normalised_rays(cal[ref])
    fx = float(cal[ref].K[0, 0])
    n_scales = decs[ref].cfg.n_scales
    coarsest = n_scales - 1
    coarse_other = cached_centroids(decs, other, coarsest, cache)  # only its centroids are used
    info: dict[str, Any] = {"per_scale_coverage": [], "per_scale_coverage_stereo": []}
    n_steps = fill_steps_for(view(ref, 0), cfg.filt.fill_steps, n_scales)
    info["fill_scales"] = [f"1/{1 << s}" for s in range(n_steps)]
    views, stereo = [], []
    for s in range(n_steps):  # scales Eq. 3 does not reach are not computed
        v_ref, v_oth = view(ref, s), view(other, s)
        q, ok = match_in_other(v_ref, v_oth, cfg.tri, coarse=coarse_other)
        views.append(v_ref)
        stereo.append(depth_from_match(rays, fx, q, ok, cal[other], R, T, cfg.tri))
    filtered = [filter_depth(d, rays, cfg.filt) for d in stereo]
    model = None
    if cfg.projector is not None:  # where the other camera cannot see: reference camera + projector
        X, x = projector_correspondences(views, filtered, rays, cfg.projector)
        model = calibrate_projector(X, x, decs[ref].scale_size(0), cfg.projector)
    info["projector_rms_px"] = None if model is None else model.rms_px
    info["projector_points"] = 0 if model is None else model.n_points
    info["projector_position_sd_mm"] = None if model is None else model.position_sd_m * 1000.0
    depths = []
    for s, (v, d, f) in enumerate(zip(views, stereo, filtered)):
        info["per_scale_coverage_stereo"].append(float(np.isfinite(f).mean()))
        if model is not None:
            col, row, valid = decs[ref].at_scale(s)
            todo = v.valid & ~np.isfinite(d) & ~mixed_codes(col, row, valid, v.u, v.v)
            dp = procam_depth(rays, fx, v.to_full(v.u), v.to_full(v.v), todo, model, cfg.tri)
            f = filter_depth(np.where(np.isfinite(d), d, dp), rays, cfg.filt)
        depths.append(f)
        info["per_scale_coverage"].append(float(np.isfinite(f).mean()))
    fused = recursive_fill(depths, n_steps)
    info["coverage_raw"] = float(np.isfinite(fused).mean())
    return fused, info


def resize_depth(depth_m: NDArray[np.float32], size: tuple[int, int]) -> NDArray[np.float32]:
    """Valid-weighted area resize of a NaN-holed depth map to (W, H); valid where >= half the area was valid."""
    if (depth_m.shape[1], depth_m.shape[0]) == tuple(size):
        return depth_m
    valid = np.isfinite(depth_m).astype(np.float32)
    num = cv2.resize(np.nan_to_num(depth_m), tuple(size), interpolation=cv2.INTER_AREA)
    den = cv2.resize(valid, tuple(size), interpolation=cv2.INTER_AREA)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    out[den < 0.5] = np.nan
    return out.astype(np.float32)


def focus_window_for(cfg: ProcessConfig, out_w: int) -> tuple[int, int]:
    """The Eq. 5 window scaled from the reference width to this output width (at least 3 x 3)."""
    f = out_w / cfg.focus_window_ref_width
    return max(3, int(round(cfg.focus_window_px[0] * f))), max(3, int(round(cfg.focus_window_px[1] * f)))


def thin_focal_length(lens_mm: float | None, pinhole_mm: float, focus_mm: float) -> tuple[float, str]:
    """Thin-lens focal length for Eq. 6: the lens's own when known, else Eq. 7, ``1/f = 1/F + 1/f_pin``.

    Args:
        lens_mm: the lens focal length from the manifest (None if unknown).
        pinhole_mm: calibrated pinhole focal length ``K[0,0] x pixel pitch`` in mm.
        focus_mm: focus distance F in mm (Eq. 5).

    Returns:
        (focal length in mm, where it came from).
    """
    if lens_mm:
        return float(lens_mm), "lens"
    return thin_lens_focal_length_mm(pinhole_mm, focus_mm), "Eq. 7 from the calibrated pinhole focal length"


def _unsaturated(img: NDArray[np.float32]) -> NDArray[np.bool_]:
    """(H, W) True where every channel of an (H, W, 3) image lies below 0.98 (``img.max(-1) < 0.98``: numpy's
    reduction over a last axis of 3 is several times slower than two element-wise maxima)."""
    return np.maximum(np.maximum(img[..., 0], img[..., 1]), img[..., 2]) < 0.98


def _exposure_ratio(dp_main: NDArray[np.float32], sharp_main: NDArray[np.float32],
                    sharp_unsaturated: NDArray[np.bool_] | None = None) -> float:
    """Ratio of mean signal DP / sharp over pixels unsaturated in both (blur preserves the mean);
    ``sharp_unsaturated``: ``_unsaturated(sharp_main)`` when already computed (one sharp frame per camera)."""
    ok = _unsaturated(dp_main)
    ok &= _unsaturated(sharp_main) if sharp_unsaturated is None else sharp_unsaturated
    if ok.mean() < 0.5:
        ok = np.ones(ok.shape, bool)
    s = float(sharp_main[ok].sum())
    if s <= 0:
        raise StageError("the sharp f/22 frame is black; cannot match its exposure")
    return float(dp_main[ok].sum()) / s


def process_scene(session: Session, cfg: ProcessConfig = ProcessConfig()) -> SceneResult:
    """Process one checked session into pairs (nothing is written here)."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    probe = read_main(session, session.cameras["cam0"].sl[-1])[0]
    raw_size = (probe.shape[1], probe.shape[0])
    out_size = cfg.out_size or (raw_size[0] // 2, raw_size[1] // 2)
    for cam, cs in session.cameras.items():  # a bad focus point fails the scene before any heavy work
        fx, fy = cs.focus_point_raw_px
        if not (0 <= fx < raw_size[0] and 0 <= fy < raw_size[1]):
            raise BadInputError(f"{cam} focus point ({fx:.0f}, {fy:.0f}) lies outside the {raw_size[0]}x{raw_size[1]} "
                                "raw image", where=session.root / "manifest.json")
    st, cal_info = calibrate_session(session, cfg, raw_size)
    timings["calibrate_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    gcfg = cfg.gray or GrayCodeConfig.for_linear_raw(*session.projector_size)
    decs = {}
    for cam in ("cam0", "cam1"):
        decs[cam], size, _ = decode_camera(session, cam, gcfg)
        if size != raw_size:
            raise BadInputError(f"{cam} structured-light frames are {size}, expected {raw_size}", where=session.root)
    timings["decode_s"] = time.perf_counter() - t0

    # issue 20: the ChArUco extrinsics checked against the structured light, refined where they do not fit
    t0 = time.perf_counter()
    views_cache: ViewCache = {}  # each camera's code views, shared by the check and both depth passes
    st, cal_info["refinement"], warnings = refine_stereo(decs, st, cfg.tri, cfg.refine, where=session.scene,
                                                         cache=views_cache)
    timings["refine_s"] = time.perf_counter() - t0

    report: dict[str, Any] = {"scene": session.scene, "manifest_scene": session.manifest.get("scene"),
                              "calibration": cal_info, "warnings": warnings, "cameras": {}}
    pairs: list[Pair] = []
    depth_out: dict[str, NDArray[np.float32]] = {}
    timings["depth_s"] = timings["views_s"] = timings["pairs_s"] = 0.0
    cams = ("cam0", "cam1")
    for cam in cams:
        cs = session.cameras[cam]
        t0 = time.perf_counter()
        depth_raw, dinfo = depth_for_camera(decs, cam, st, cfg, views_cache)
        if cam == cams[-1]:
            views_cache.clear()  # both depth passes done
        depth_m = resize_depth(depth_raw, out_size)
        depth_out[cam] = depth_m
        timings["depth_s"] += time.perf_counter() - t0

        t0 = time.perf_counter()
        sx, sy = out_size[0] / raw_size[0], out_size[1] / raw_size[1]
        fx, fy = cs.focus_point_raw_px
        fp_out = ((fx + 0.5) * sx - 0.5, (fy + 0.5) * sy - 0.5)
        window = focus_window_for(cfg, out_size[0])
        try:
            F_mm = focus_distance(depth_m * 1000.0, fp_out, FocusConfig(window_px=window))
        except StageError as exc:
            raise StageError(f"{cam}: {exc.message}", where=session.root) from exc
        Kout = (st.cam0 if cam == "cam0" else st.cam1).scaled(sx, sy).K
        pitch_mm = cs.sensor_size_mm[0] / out_size[0]
        f_pin_mm = float(Kout[0, 0]) * pitch_mm
        f_thin, f_source = thin_focal_length(cs.focal_length_mm, f_pin_mm, F_mm)
        sharp_fr = read_frames(session, cs.sharp)
        sharp_main, _, _ = dp_views(sharp_fr, session.aux_view)
        sharp_main = resize_image(sharp_main, out_size)
        sharp_ok = _unsaturated(sharp_main)
        timings["views_s"] += time.perf_counter() - t0
        cam_rep: dict[str, Any] = {
            "depth_coverage": float(np.isfinite(depth_m).mean()), "focus_distance_mm": F_mm,
            "focus_point_px": list(fp_out), "focus_window_px": list(window), "focal_length_mm": f_thin,
            "focal_length_source": f_source, "pinhole_focal_length_mm": f_pin_mm, **dinfo, "pairs": [],
        }
        for N, path in cs.dp.items():
            t0 = time.perf_counter()
            fr = read_frames(session, path)
            main, left, right = (resize_image(a, out_size) for a in dp_views(fr, session.aux_view))
            ratio = _exposure_ratio(main, sharp_main, sharp_ok)
            timings["views_s"] += time.perf_counter() - t0
            t0 = time.perf_counter()
            coc = coc_diameter_px(np.nan_to_num(depth_m * 1000.0, nan=0.0), F_mm, f_thin, N, pitch_mm).astype(np.float32)
            pid = f"{session.scene}_{cam}_f{N:g}"
            params = PairParams(
                pair_id=pid, scene=session.scene, camera=cam, f_number=float(N), focus_distance_mm=float(F_mm),
                focal_length_mm=float(f_thin), pixel_pitch_mm=float(pitch_mm),
                focus_point_px=(float(fp_out[0]), float(fp_out[1])), image_size=(int(out_size[0]), int(out_size[1])),
                extra={"exposure": {"sharp_gain": ratio}, "sharp_f_number": 22.0, "reprojection_error_px": st.rms_px,
                       "depth_coverage": cam_rep["depth_coverage"], "aux_view": session.aux_view,
                       "source": "dp5k process"},
            )
            pairs.append(Pair(params, np.clip(sharp_main * ratio, 0, 1), np.clip(left, 0, 1), np.clip(right, 0, 1),
                                  np.nan_to_num(depth_m * 1000.0, nan=0.0).astype(np.float32), coc))
            cam_rep["pairs"].append(pid)
            timings["pairs_s"] += time.perf_counter() - t0
        report["cameras"][cam] = cam_rep
    report["timings"] = timings
    report["image_size"] = list(out_size)
    report["raw_size"] = list(raw_size)
    return SceneResult(session.scene, pairs, st, report, depth_out)
