"""Studio speed: a full simulated session per stage, one DP pair per output size, and a 30-pair dataset.

Run: ``.venv/bin/python benchmarks/bench_studio.py [--session small|medium|paper|none] [--scene demo01]
[--sizes 420x280,840x560,1680x1120] [--skip-dataset]``.

Part A, the session (issue 22 target 6: 110 raw frames of 3360 x 2240 at ``paper`` in under 10 minutes):
``dp5k_testing.sim_session.write_session`` renders and writes what ``dp5k capture --sim`` takes (3 ChArUco
views x 2 cameras, 5 f-numbers + the f/22 sharp frame x 2 cameras, 46 structured-light projections x 2
cameras) and the table splits its wall and CPU seconds (CPU: all threads; on a loaded shared machine wall
time inflates, CPU time much less) into stages: ray casting (``view_geometry``), DP plans (``plan_dp``: CoC
layers of a depth map), DP renders (``DPPlan.render``), the sensor (``expose_raw``), writing the DNG files
(+ their checksums: the floor, what a session costs if rendering were free) and the rest. Part B: one DP
pair (ray casting + left/right views) per output size, as before. Every table prints the date, the load
average and the git commit.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import os
import resource
import subprocess
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import dp5k_studio.dp_optics as dp_optics
import dp5k_studio.studio as studio_mod
import dp5k_testing.sim_session as sim_session
from dp5k_studio import LensSetting, make_dataset, make_rig, make_scene, render_dp
from dp5k_studio.render import view_geometry
from run_info import record_result

F_NUMBERS = (1.8, 2.0, 2.8, 4.0, 5.6)
"""The paper's five DP apertures."""


def stamp() -> str:
    """Date, 1/5/15-min load averages, core count and git commit, for every table."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).resolve().parent, check=False).stdout.strip() or "?"
    except OSError:
        commit = "?"
    l1, l5, l15 = os.getloadavg()
    return (f"{datetime.datetime.now().isoformat(timespec='seconds')}, load average {l1:.1f} / {l5:.1f} / {l15:.1f} "
            f"on {os.cpu_count()} cores, commit {commit}")


class StageClock:
    """Exclusive wall and CPU seconds per stage: a stage called inside another is taken out of the outer one."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self._stack: list[list[float]] = []

    def wrap(self, name: str, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            self._stack.append([0.0, 0.0])
            w0, c0 = time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                dw, dc = time.perf_counter() - w0, time.process_time() - c0
                inner_w, inner_c = self._stack.pop()
                self.wall[name] += dw - inner_w
                self.cpu[name] += dc - inner_c
                self.calls[name] += 1
                if self._stack:
                    self._stack[-1][0] += dw
                    self._stack[-1][1] += dc
        return timed


def bench_session(scale: str, scene: str, progress: bool = False) -> None:
    """Part A: render and write one full session at ``scale``; print the stage table (and, with ``progress``,
    the running CPU seconds per stage after every raw file)."""
    clock = StageClock()
    patches = [(studio_mod, "view_geometry", "ray casting (view_geometry)"),
               (studio_mod, "plan_dp", "DP plans (plan_dp)"),
               (getattr(dp_optics, "DPPlan", None), "render", "DP renders (DPPlan.render)"),
               (studio_mod, "render_dp", "DP renders (render_dp, before the plan)"),
               (studio_mod, "expose_raw", "sensor (expose_raw)"),
               (sim_session, "write_dual_pixel_dng", "writing the DNG files (floor)"),
               (sim_session, "sha256_file", "writing the DNG files (floor)")]
    patches = [p for p in patches if hasattr(p[0], p[1])]  # an older revision has fewer stages (the rest grows)
    saved = [(obj, attr, getattr(obj, attr)) for obj, attr, _ in patches]
    for obj, attr, name in patches:
        setattr(obj, attr, clock.wrap(name, getattr(obj, attr)))
    print(f"\nA. full session, scene {scene}, scale {scale}: {stamp()}", flush=True)
    w0, c0 = time.perf_counter(), time.process_time()
    if progress:  # one line per raw file written: a run cut short still tells what its frames cost
        write = sim_session.write_dual_pixel_dng

        def write_and_report(path, *args, **kwargs):
            write(path, *args, **kwargs)
            stages = ", ".join(f"{n.split(' (')[0]} {clock.cpu[n]:.0f}" for n in dict.fromkeys(x for _, _, x in patches))
            print(f"  {Path(path).parent.name}/{Path(path).name}: {time.perf_counter() - w0:.0f} s wall, "
                  f"{time.process_time() - c0:.0f} s CPU ({stages}), load {os.getloadavg()[0]:.1f}", flush=True)

        sim_session.write_dual_pixel_dng = write_and_report
    try:
        with tempfile.TemporaryDirectory(prefix="bench-studio-") as tmp:
            sim_session.write_session(Path(tmp), scene, scale=scale, f_numbers=F_NUMBERS)
            wall, cpu = time.perf_counter() - w0, time.process_time() - c0
            files = sorted(Path(tmp).rglob("*.dng"))
            n_bytes = sum(f.stat().st_size for f in files)
            size = (make_rig(scale).cameras[0].width, make_rig(scale).cameras[0].height)
    finally:
        for obj, attr, fn in saved:
            setattr(obj, attr, fn)
    print(f"{len(files)} raw frames of {size[0]} x {size[1]}, {n_bytes / 1e9:.2f} GB; "
          f"peak memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB; after: {stamp()}")
    print("\n| stage | calls | wall s | CPU s |\n|---|---|---|---|")
    rows = []
    for name in dict.fromkeys(n for _, _, n in patches):
        print(f"| {name} | {clock.calls[name]} | {clock.wall[name]:.1f} | {clock.cpu[name]:.1f} |")
        rows.append([name, clock.calls[name], f"{clock.wall[name]:.1f}", f"{clock.cpu[name]:.1f}"])
    rest_w, rest_c = wall - sum(clock.wall.values()), cpu - sum(clock.cpu.values())
    print(f"| the rest (radiance, diffraction, focus, board, manifest) | | {rest_w:.1f} | {rest_c:.1f} |")
    print(f"| **session total** | | **{wall:.1f}** | **{cpu:.1f}** |")
    floor = clock.wall["writing the DNG files (floor)"]
    print(f"\nsession / floor (writing the raw files): {wall / max(floor, 1e-9):.1f} x; target: under 600 s wall at paper scale")
    rows += [["the rest (radiance, diffraction, focus, board, manifest)", "", f"{rest_w:.1f}", f"{rest_c:.1f}"],
             ["**session total**", "", f"**{wall:.1f}**", f"**{cpu:.1f}**"]]
    record_result(f"speed-studio-session-{scale}", f"Studio: a simulated session, scene {scene}, {scale} scale",
                  ["stage", "calls", "wall s", "CPU s"], rows,
                  notes=f"{len(files)} raw frames of {size[0]} x {size[1]}, {n_bytes / 1e9:.2f} GB; peak memory "
                        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB; {wall / max(floor, 1e-9):.1f} x "
                        "the floor of writing the raw files; target: under 600 s wall at paper scale.")


def bench_pair(size: tuple[int, int], scene_name: str, f_number: float, supersample: int) -> tuple[float, float, float]:
    """(geometry wall s, DP pair wall s, total CPU s) for one camera at ``size``."""
    W, H = size
    rig = make_rig(6720.0 / W)
    cam = rig.cameras[0].scaled(W, H)
    scene = make_scene(scene_name, rig)
    c0 = time.process_time()
    t0 = time.perf_counter()
    geom = view_geometry(scene, cam, None, (), supersample)
    rad = geom.radiance(None)
    t1 = time.perf_counter()
    Xc = cam.R @ scene.focus_target_m + cam.t
    hidden = (geom.hidden_radiance(None), geom.hidden["depth_m"] * 1000.0)
    render_dp(rad, geom.depth_m * 1000.0, LensSetting(85.0, f_number, float(Xc[2] * 1000.0), cam.pixel_pitch_mm), hidden=hidden)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1, time.process_time() - c0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", default="small", help="scale of the full session (small, medium, paper) or none")
    ap.add_argument("--sizes", default="420x280,840x560,1680x1120", help="DP pair sizes, or none")
    ap.add_argument("--scene", default="demo01")
    ap.add_argument("--f-number", type=float, default=1.8)
    ap.add_argument("--supersample", type=int, default=1)
    ap.add_argument("--skip-dataset", action="store_true")
    ap.add_argument("--progress", action="store_true", help="a line per raw file written (long paper-scale runs)")
    a = ap.parse_args()
    if a.session != "none":
        bench_session(a.session, a.scene, a.progress)
    if a.sizes != "none":
        print(f"\nB. one DP pair, scene {a.scene}, f/{a.f_number}, supersample {a.supersample}: {stamp()}")
        print(f"\n| size | Mpx | geometry s | DP pair s | wall s | CPU s | Mpx/s |\n|---|---|---|---|---|---|---|")
        rows = []
        for text in a.sizes.split(","):
            W, H = (int(v) for v in text.split("x"))
            g, d, cpu = bench_pair((W, H), a.scene, a.f_number, a.supersample)
            mpx = W * H / 1e6
            print(f"| {W} x {H} | {mpx:.2f} | {g:.2f} | {d:.2f} | {g + d:.2f} | {cpu:.2f} | {mpx / (g + d):.2f} |")
            rows.append([f"{W} x {H}", f"{mpx:.2f}", f"{g:.2f}", f"{d:.2f}", f"{g + d:.2f}", f"{cpu:.2f}", f"{mpx / (g + d):.2f}"])
        record_result("speed-studio-pair", f"Studio: one DP pair (ray casting + both views), scene {a.scene}, f/{a.f_number}",
                      ["size", "Mpx", "geometry s", "DP pair s", "wall s", "CPU s", "Mpx/s"], rows)
    if not a.skip_dataset:
        with tempfile.TemporaryDirectory() as tmp:
            c0, t0 = time.process_time(), time.perf_counter()
            make_dataset(os.path.join(tmp, "ds"), scenes=3, size=(288, 192))
            print(f"\nmake_dataset: 30 pairs at 288x192 (3 scenes x 2 cameras x 5 f-numbers): "
                  f"{time.perf_counter() - t0:.1f} s wall, {time.process_time() - c0:.1f} s CPU; {stamp()}")
            record_result("speed-studio-dataset", "Studio: make_dataset, 30 pairs at 288 x 192 (3 scenes x 2 cameras x 5 f-numbers)",
                          ["wall s", "CPU s"], [[f"{time.perf_counter() - t0:.1f}", f"{time.process_time() - c0:.1f}"]])


if __name__ == "__main__":
    main()
