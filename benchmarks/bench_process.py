"""Processing benchmark (prints tables; not a timed test).

Part A -- Gray-code decoding, side by side in one run on the same images: a stereo pair of 1680x1120 cameras
looking at a tilted plane lit by a 1920x1200 projector (44 patterns + white + black, 8-bit PNG files), decoded
by dp5k's decoder and by OpenCV contrib's ``structured_light.GrayCodePattern.decode``; agreement with the
rendering's true projector pixel; and the floor: reading the 92 images once.

Part B -- one scene end to end through ``dp5k process`` (a studio session; ``--scale paper`` for the paper's
3360x2240 raw / 1680x1120 output, default ``medium``), with the time of each step from the scene report, the
peak memory of the process and the machine's load average, against the floor measured in the same run: reading
every raw file of the session once, each as the pipeline needs it (main frame of the ChArUco and
structured-light shots, both frames of the DP and sharp shots). Depth error and coverage against the studio's
truth (``ground_truth/`` of the session). Then the outlier filter: camera 0's depth step run with the grid filter
(the default) and with Open3D's ``remove_statistical_outlier`` (before issue 22) on the same decoded session:
seconds, the fraction of pixels whose validity differs, and each one's error against the truth.

Part C -- the outlier filter alone at the paper's raw size (3360 x 2240, 7.5 M points; ``--filter-size``) on a
synthetic organised cloud (a tilted plane with a 0.4 m step, a hole, 0.5 % spikes), Open3D against the grid
filter in the same run: seconds and the fraction of valid pixels they decide differently. Part B's depth step at
paper size ran this filter 6 times per scene.

Rendering a paper-scale session (110 raw frames of 7.5 MP) takes tens of minutes on a 2-core machine:
``--keep DIR`` keeps the rendered session there and a later run with the same ``--keep`` reuses it, so the
processing can be timed again without rendering.

    .venv/bin/python benchmarks/bench_process.py [--scale medium|paper] [--scene wall] [--keep DIR]
                                                 [--skip-decode] [--skip-e2e] [--skip-filter]
                                                 [--filter-size 3360x2240] [--skip-filter-size] [--filter-only]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np


from dp5k_process.graycode import GrayCodeConfig, decode_graycode, opencv_patterns
from dp5k_testing.procam_synth import PlaneScene, look_at_rig, render_projection, world_points
from run_info import recording


def _true_proj(scene, proj, cam):
    Xw = world_points(scene, cam["K"], cam["dist"], cam["R"], cam["t"], cam["size"], 1)
    Xp = Xw.reshape(-1, 3) @ proj["R"].T + proj["t"]
    uv, _ = cv2.projectPoints(np.nan_to_num(Xp), np.zeros(3), np.zeros(3), proj["K"], proj["dist"])
    return uv.reshape(Xw.shape[:2] + (2,))


def part_a(tmp: Path) -> None:
    W, H, Wp, Hp = 1680, 1120, 1920, 1200
    cam0, cam1, proj = look_at_rig(baseline=0.3, z=2.0, f_px=3967.0, size=(W, H), proj_size=(Wp, Hp), proj_f=2880.0)
    scene = PlaneScene([(np.array([0.15, 0.05, 1.0]), 2.0, None)])
    pats = opencv_patterns(Wp, Hp) + [np.full((Hp, Wp), 255, np.uint8), np.zeros((Hp, Wp), np.uint8)]
    rng = np.random.default_rng(0)
    truth = {}
    t0 = time.perf_counter()
    for name, cam in (("cam0", cam0), ("cam1", cam1)):
        imgs, _ = render_projection(pats, proj, cam, scene, supersample=1, ambient=0.05, gain=0.8, noise=0.01,
                                    rng=rng, blur_sigma=0.7)
        (tmp / name).mkdir(parents=True, exist_ok=True)
        for k, im in enumerate(imgs):
            cv2.imwrite(str(tmp / name / f"sl_{k:02d}.png"), np.clip(im * 255, 0, 255).astype(np.uint8))
        truth[name] = _true_proj(scene, proj, cam)
    print(f"(rendered 2 x 46 images of {W}x{H} in {time.perf_counter() - t0:.1f} s)\n")

    t0 = time.perf_counter()
    imgs = {c: [cv2.imread(str(tmp / c / f"sl_{k:02d}.png"), cv2.IMREAD_GRAYSCALE) for k in range(46)]
            for c in ("cam0", "cam1")}
    t_read = time.perf_counter() - t0

    cfg = GrayCodeConfig(Wp, Hp)  # 8-bit thresholds 5 / 40, one weak bit tolerated
    cfg0 = GrayCodeConfig(Wp, Hp, max_weak_bits=0)  # OpenCV's rule
    t0 = time.perf_counter()
    ours = {c: decode_graycode(imgs[c][:44], imgs[c][44], imgs[c][45], 255.0, cfg) for c in imgs}
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    ours0 = {c: decode_graycode(imgs[c][:44], imgs[c][44], imgs[c][45], 255.0, cfg0) for c in imgs}
    t_ours0 = time.perf_counter() - t0

    def streamed(c: str):
        load = lambda i: cv2.imread(str(tmp / c / f"sl_{i:02d}.png"), cv2.IMREAD_GRAYSCALE)  # noqa: E731
        return decode_graycode(load, load(44), load(45), 255.0, cfg)

    t0 = time.perf_counter()
    for c in imgs:
        streamed(c)
    t_stream = time.perf_counter() - t0

    gc = cv2.structured_light.GrayCodePattern.create(Wp, Hp)
    gc.setWhiteThreshold(5)
    gc.setBlackThreshold(40)
    t0 = time.perf_counter()
    gc.decode([imgs["cam0"][:44], imgs["cam1"][:44]], None, [imgs["cam0"][45], imgs["cam1"][45]],
              [imgs["cam0"][44], imgs["cam1"][44]], cv2.structured_light.DECODE_3D_UNDERWORLD)
    t_cv = time.perf_counter() - t0

    def agree(dec, c):
        col, row, valid = dec.at_scale(0)
        tx, ty = np.rint(truth[c][..., 0]), np.rint(truth[c][..., 1])
        inside = (tx >= 0) & (tx < Wp) & (ty >= 0) & (ty < Hp)
        exact = valid & (col == tx) & (row == ty)
        near = valid & (np.abs(col - tx) <= 1) & (np.abs(row - ty) <= 1)
        return valid[inside].mean(), exact[inside].sum() / max(1, valid[inside].sum()), near[inside].sum() / max(1, valid[inside].sum())

    rng = np.random.default_rng(1)
    ys, xs = rng.integers(0, H, 3000), rng.integers(0, W, 3000)
    n_ok = n_exact = n_near = n_in = 0
    for y, x in zip(ys, xs):
        tx, ty = np.rint(truth["cam0"][y, x])
        if not (0 <= tx < Wp and 0 <= ty < Hp):
            continue
        n_in += 1
        err, (px, py) = gc.getProjPixel(imgs["cam0"][:44], int(x), int(y))
        lit = abs(int(imgs["cam0"][44][y, x]) - int(imgs["cam0"][45][y, x])) > 40
        if not err and lit:
            n_ok += 1
            n_exact += (px == tx and py == ty)
            n_near += (abs(px - tx) <= 1 and abs(py - ty) <= 1)
    a1, a0 = agree(ours["cam0"], "cam0"), agree(ours0["cam0"], "cam0")
    print("| decoder (stereo pair, 2 x 46 images 1680x1120, projector 1920x1200) | time s | vs OpenCV | "
          "valid px (cam0) | code exact | code +-1 |")
    print("|---|---|---|---|---|---|")
    print(f"| OpenCV contrib GrayCodePattern.decode (DECODE_3D_UNDERWORLD, thresholds 5/40) | {t_cv:.2f} | 1x | "
          f"{n_ok / max(1, n_in):.3f} (3000 sampled, getProjPixel) | {n_exact / max(1, n_ok):.4f} | {n_near / max(1, n_ok):.4f} |")
    print(f"| dp5k decode_graycode, OpenCV's rule (max_weak_bits=0), images in memory | {t_ours0:.2f} | "
          f"{t_cv / t_ours0:.1f}x | {a0[0]:.3f} | {a0[1]:.4f} | {a0[2]:.4f} |")
    print(f"| dp5k decode_graycode, default (one weak bit), images in memory | {t_ours:.2f} | {t_cv / t_ours:.1f}x | "
          f"{a1[0]:.3f} | {a1[1]:.4f} | {a1[2]:.4f} |")
    print(f"| dp5k decode_graycode streaming from PNG files (read + decode) | {t_stream:.2f} | "
          f"{(t_cv + t_read) / t_stream:.1f}x vs read+OpenCV | | | |")
    print(f"| floor: reading the 92 PNG images once (cv2.imread) | {t_read:.2f} | | | | |")
    print(f"\nstreaming decode is {t_stream / t_read:.2f}x the read-only floor "
          f"({t_stream - t_read:.2f} s of decoding on top of {t_read:.2f} s of reading); OpenCV's decode also "
          "computes its disparity map (bucketing), which dp5k does later in its matching step.\n")


def read_floor_s(session_dir: Path) -> tuple[float, float, int]:
    """Wall and CPU seconds (this process) to read every raw file of the session once as the pipeline needs it,
    and the number of files."""
    from dp5k_common.rawfile import read_dual_pixel, read_frame

    files = json.loads((session_dir / "manifest.json").read_text())["files"]
    t0, c0 = time.perf_counter(), time.process_time()
    for f in files:
        if f["kind"] in ("dp", "sharp"):
            read_dual_pixel(session_dir / f["path"])
        else:
            read_frame(session_dir / f["path"])
    return time.perf_counter() - t0, time.process_time() - c0, len(files)


def load_truth_m(session_dir: Path, cam: str) -> np.ndarray:
    """The studio's true depth (metres, NaN = no surface) at raw resolution: ``ground_truth/depth_<cam>.npy``
    (``dp5k_testing.sim_session``) or ``ground_truth/<cam>_depth_mm.png`` (``dp5k capture --sim``)."""
    npy = session_dir / "ground_truth" / f"depth_{cam}.npy"
    if npy.is_file():
        return np.load(npy)
    mm = cv2.imread(str(session_dir / "ground_truth" / f"{cam}_depth_mm.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    return np.where(mm > 0, mm / 1000.0, np.nan)


def truth_error(depth_m: np.ndarray, truth_m: np.ndarray) -> tuple[float, float, float]:
    """Median abs. relative error and fraction > 2 % off over the valid pixels, and coverage of the pixels with a
    true depth; ``truth_m`` at raw resolution, halved (2 x 2 mean) when ``depth_m`` is the half-size output."""
    from dp5k_testing.truth import half

    if truth_m.shape != depth_m.shape:
        truth_m = half(truth_m, "mean")
    ok = np.isfinite(depth_m) & np.isfinite(truth_m) & (truth_m > 0)
    rel = np.abs(depth_m[ok] - truth_m[ok]) / truth_m[ok]
    has_truth = np.isfinite(truth_m) & (truth_m > 0)
    return float(np.median(rel)), float((rel > 0.02).mean()), float(np.isfinite(depth_m)[has_truth].mean())


def filter_comparison(session_dir: Path) -> None:
    """Camera 0's depth step with the grid filter and with Open3D's, on the same calibrated, decoded session."""
    import dataclasses
    import os

    from dp5k_process.filters import FilterConfig
    from dp5k_process.graycode import GrayCodeConfig
    from dp5k_process.pipeline import ProcessConfig, calibrate_session, decode_camera, depth_for_camera
    from dp5k_process.refine import refine_stereo
    from dp5k_process.session import load_session

    session = load_session(session_dir)
    cfg = ProcessConfig()
    decs = {}
    for cam in ("cam0", "cam1"):
        decs[cam], raw_size, _ = decode_camera(session, cam, GrayCodeConfig.for_linear_raw(*session.projector_size))
    st, _ = calibrate_session(session, cfg, raw_size)
    st, _, _ = refine_stereo(decs, st, cfg.tri, cfg.refine, where=session.scene)
    truth = load_truth_m(session_dir, "cam0")
    res = {}
    for method in ("grid", "open3d"):
        mcfg = dataclasses.replace(cfg, filt=dataclasses.replace(FilterConfig(), sor_method=method))
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        depth, _ = depth_for_camera(decs, "cam0", st, mcfg)
        res[method] = (time.perf_counter() - t0, depth, load0)
    v_g, v_o = np.isfinite(res["grid"][1]), np.isfinite(res["open3d"][1])
    print(f"\n| cam0 depth step ({raw_size[0]}x{raw_size[1]} raw grid), outlier filter | seconds | load (1 min) | "
          "coverage of true-depth px | median abs. rel. error | > 2 % off |")
    print("|---|---|---|---|---|---|")
    for method, label in (("grid", "grid (issue 22, default)"), ("open3d", "Open3D remove_statistical_outlier (before)")):
        t, d, ld = res[method]
        med, off, cov = truth_error(d, truth)
        print(f"| {label} | {t:.2f} | {ld:.2f} | {100 * cov:.2f} % | {100 * med:.3f} % | {100 * off:.2f} % |")
    both = v_g & v_o
    print(f"\nfused masks: {100 * (v_g != v_o).mean():.3f} % of the pixels differ ({(v_g & ~v_o).sum()} valid only with "
          f"the grid filter, {(v_o & ~v_g).sum()} only with Open3D); on the {both.sum()} pixels both keep the depths "
          f"differ by {100 * np.median(np.abs(res['grid'][1][both] - res['open3d'][1][both]) / res['open3d'][1][both]):.4f} % "
          "(median)")


def part_b(scale: str, tmp: Path, scene: str = "wall", keep: Path | None = None, compare: bool = True) -> None:
    import os
    import resource

    from dp5k_process.package import process_sessions
    from dp5k_process.pipeline import ProcessConfig
    from dp5k_testing.sim_session import write_session

    raw = (keep or tmp) / "raw"
    t_render = None
    if not (raw / scene / "manifest.json").is_file():
        t0 = time.perf_counter()
        write_session(raw, scene, scale=scale, f_numbers=(1.8, 2.0, 2.8, 4.0, 5.6), board_on_wall=scene == "wall")
        t_render = time.perf_counter() - t0
    out = tmp / "out"
    load_f = os.getloadavg()
    t_floor, c_floor, n_files = read_floor_s(raw / scene)
    load0 = os.getloadavg()
    t0, c0 = time.perf_counter(), time.process_time()
    process_sessions(raw, out, ProcessConfig())
    t_total, c_total = time.perf_counter() - t0, time.process_time() - c0
    load1 = os.getloadavg()
    peak_gib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    rep = json.loads((out / "reports" / scene / "report.json").read_text())
    print(f"| dp5k process, one scene ({scene}, {scale}: raw {rep['raw_size'][0]}x{rep['raw_size'][1]}, output "
          f"{rep['image_size'][0]}x{rep['image_size'][1]}, 2 cameras x 5 f-numbers) | seconds | x read floor | "
          "load (1 min) |")
    print("|---|---|---|---|")
    print(f"| floor: reading the {n_files} raw files once | {t_floor:.2f} | 1.00 | {load_f[0]:.2f} |")
    for k, v in rep["timings"].items():
        print(f"| {k[:-2]} | {v:.2f} | {v / t_floor:.2f} | |")
    print(f"| total incl. writing pairs, report, contact sheet | {t_total:.2f} | **{t_total / t_floor:.2f}** | "
          f"{load0[0]:.2f} -> {load1[0]:.2f} |")
    print(f"\n| CPU time of this process (less sensitive to load than wall time) | CPU seconds | x read floor |")
    print("|---|---|---|")
    print(f"| floor: reading the {n_files} raw files once | {c_floor:.2f} | 1.00 |")
    print(f"| dp5k process, the whole scene | {c_total:.2f} | **{c_total / c_floor:.2f}** |")
    cams = rep["cameras"]
    rendered = (f"session rendered by the studio in {t_render:.1f} s" if t_render is not None
                else f"session reused from {raw}")
    print(f"\n| depth against the studio's truth (output {rep['image_size'][0]}x{rep['image_size'][1]}) | coverage of "
          "true-depth px | median abs. rel. error | > 2 % off |")
    print("|---|---|---|---|")
    for cam in ("cam0", "cam1"):
        pid = cams[cam]["pairs"][0]
        mm = cv2.imread(str(out / "pairs" / pid / "depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
        med, off, cov = truth_error(np.where(mm > 0, mm / 1000.0, np.nan), load_truth_m(raw / scene, cam))
        print(f"| {cam} | {100 * cov:.2f} % | {100 * med:.3f} % | {100 * off:.2f} % |")
    print(f"\n({rendered}; depth coverage {cams['cam0']['depth_coverage']:.3f} / {cams['cam1']['depth_coverage']:.3f}, "
          f"reprojection error {rep['calibration']['reprojection_error_px']:.3f} px; peak memory of this process "
          f"{peak_gib:.1f} GiB{' (rendering included)' if t_render is not None else ''}; "
          f"fill scales {', '.join(cams['cam0'].get('fill_scales', []))}; load average (1, 5, 15 min) "
          f"{', '.join(f'{x:.2f}' for x in load0)} before / {', '.join(f'{x:.2f}' for x in load1)} after processing)")
    if compare:
        filter_comparison(raw / scene)


def part_c(size: tuple[int, int]) -> None:
    import os

    from dp5k_process.filters import statistical_outliers
    from dp5k_process.grid_outliers import grid_outlier_mask

    W, H = size
    rng = np.random.default_rng(0)
    xs, ys = np.meshgrid(np.linspace(-0.2, 0.2, W, dtype=np.float32), np.linspace(-0.15, 0.15, H, dtype=np.float32))
    rays = np.stack([xs, ys], -1)
    depth = (1.5 + 0.3 * xs + 0.0003 * rng.standard_normal((H, W), dtype=np.float32)).astype(np.float32)
    depth[:, W // 2:] += 0.4
    spikes = rng.random((H, W)) < 0.005
    depth[spikes] += rng.uniform(-0.3, 0.3, int(spikes.sum())).astype(np.float32)
    depth[H // 3:H // 3 + H // 10, W // 4:W // 4 + W // 10] = np.nan
    valid = np.isfinite(depth)
    res = {}
    for name in ("grid", "open3d"):
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        if name == "grid":
            removed = grid_outlier_mask(depth, rays)
        else:
            removed = np.isnan(statistical_outliers(depth, rays, 20, 2.0)) & valid
        res[name] = (time.perf_counter() - t0, removed, load0)
    print(f"\n| outlier filter alone, synthetic organised cloud {W}x{H} ({valid.sum() / 1e6:.2f} M points) | seconds | "
          "load (1 min) | removed | planted spikes removed |")
    print("|---|---|---|---|---|")
    for name, label in (("open3d", "Open3D remove_statistical_outlier(20, 2.0)"), ("grid", "grid filter (k = 20, 7 x 7 window)")):
        t, rm, ld = res[name]
        print(f"| {label} | {t:.2f} | {ld:.2f} | {100 * rm[valid].mean():.3f} % | {100 * rm[spikes & valid].mean():.1f} % |")
    print(f"\nthe two differ on {100 * (res['grid'][1] != res['open3d'][1])[valid].mean():.3f} % of the valid pixels; "
          f"grid filter {res['open3d'][0] / res['grid'][0]:.1f}x faster in this run")


def stamp() -> str:
    """Date, git commit and CPU count, printed above every run's tables (each row carries its own load)."""
    import os
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    return f"{time.strftime('%Y-%m-%d %H:%M')}, commit {commit}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", default="medium", help="studio scale for part B (small, medium, paper)")
    ap.add_argument("--scene", default="wall", help="studio scene for part B (preset or seed)")
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep the rendered part-B session in this folder and reuse it when it is already there")
    ap.add_argument("--skip-e2e", action="store_true")
    ap.add_argument("--skip-decode", action="store_true")
    ap.add_argument("--skip-filter", action="store_true", help="leave out part B's grid vs Open3D filter comparison")
    ap.add_argument("--filter-only", action="store_true",
                    help="part B's filter comparison alone, on the kept session KEEP/raw/SCENE (e.g. from dp5k capture --sim)")
    ap.add_argument("--filter-size", default="3360x2240", help="part C's synthetic depth map WxH")
    ap.add_argument("--skip-filter-size", action="store_true", help="leave out part C")
    args = ap.parse_args()
    cv2.setNumThreads(0)
    print(stamp() + "\n")
    with tempfile.TemporaryDirectory() as d:
        if not args.skip_decode:
            with recording("speed-process-decode", "Processing: Gray-code decoding, dp5k against OpenCV contrib"):
                part_a(Path(d) / "a")
        if args.filter_only:
            filter_comparison(args.keep / "raw" / args.scene)
        elif not args.skip_e2e:
            with recording(f"speed-process-{args.scale}", f"Processing: one {args.scene} scene at {args.scale} scale against the read floor"):
                part_b(args.scale, Path(d) / "b", args.scene, args.keep, compare=not args.skip_filter)
        if not args.skip_filter_size:
            w, h = (int(v) for v in args.filter_size.lower().split("x"))
            with recording("speed-process-filter", f"Processing: the outlier filter alone at {w} x {h}"):
                part_c((w, h))


if __name__ == "__main__":
    main()
