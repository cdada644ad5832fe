"""Studio speed: one DP pair (ray casting + left/right views) per output size, and a 30-pair dataset.

Run: ``.venv/bin/python benchmarks/bench_studio.py [--sizes 420x280,840x560,1680x1120] [--scene demo01]``.
Prints a table: size, Mpx, geometry (ray casting incl. hidden surfaces), DP optics at f/1.8, total wall
seconds, total CPU seconds (all threads; on a loaded shared machine wall time inflates, CPU time does not),
Mpx/s (wall). Target (issue 3): a DP pair at 1680 x 1120 within 10 s on the 2-core dev machine, cost linear
in pixel count; a 30-pair 288 x 192 dataset well under a minute.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

from dp5k_studio import LensSetting, make_dataset, make_rig, make_scene, render_dp
from dp5k_studio.render import view_geometry


def bench(size: tuple[int, int], scene_name: str, f_number: float, supersample: int) -> tuple[float, float, float]:
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
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="420x280,840x560,1680x1120")
    ap.add_argument("--scene", default="demo01")
    ap.add_argument("--f-number", type=float, default=1.8)
    ap.add_argument("--supersample", type=int, default=1)
    ap.add_argument("--skip-dataset", action="store_true")
    a = ap.parse_args()
    print(f"scene {a.scene}, f/{a.f_number}, supersample {a.supersample}, load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"{'size':>11} {'Mpx':>6} {'geometry s':>11} {'DP pair s':>10} {'wall s':>7} {'CPU s':>6} {'Mpx/s':>6}")
    for text in a.sizes.split(","):
        W, H = (int(v) for v in text.split("x"))
        g, d, cpu = bench((W, H), a.scene, a.f_number, a.supersample)
        mpx = W * H / 1e6
        print(f"{W:>5}x{H:<5} {mpx:6.2f} {g:11.2f} {d:10.2f} {g + d:7.2f} {cpu:6.2f} {mpx / (g + d):6.2f}")
    if not a.skip_dataset:
        with tempfile.TemporaryDirectory() as tmp:
            c0, t0 = time.process_time(), time.perf_counter()
            make_dataset(os.path.join(tmp, "ds"), scenes=3, size=(288, 192))
            print(f"make_dataset: 30 pairs at 288x192 (3 scenes x 2 cameras x 5 f-numbers): "
                  f"{time.perf_counter() - t0:.1f} s wall, {time.process_time() - c0:.1f} s CPU")


if __name__ == "__main__":
    main()
