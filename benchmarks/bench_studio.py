"""Studio speed: one DP pair (left + right views) per output size; cost should be linear in pixel count.

Run: ``.venv/bin/python benchmarks/bench_studio.py [--sizes 288x192,840x560,1680x1120] [--scene demo01]``.
Prints a table: size, Mpx, geometry (ray casting) seconds, DP optics seconds at f/1.8, total, Mpx/s.
Target (issue 3): a DP pair at 1680 x 1120 within 10 s on the 2-core dev machine.
"""

from __future__ import annotations

import argparse
import time


from dp5k_capture.sim.studio import LensSetting, make_rig, make_scene, render_dp
from dp5k_capture.sim.studio.render import view_geometry


def bench(size: tuple[int, int], scene_name: str, f_number: float, supersample: int) -> tuple[float, float]:
    W, H = size
    rig = make_rig(6720.0 / W)
    cam = rig.cameras[0].scaled(W, H)
    scene = make_scene(scene_name, rig)
    t0 = time.perf_counter()
    geom = view_geometry(scene, cam, None, (), supersample)
    rad = geom.radiance(None)
    t1 = time.perf_counter()
    Xc = cam.R @ scene.focus_target_m + cam.t
    F_mm = float(Xc[2] * 1000.0)
    render_dp(rad, geom.depth_m * 1000.0, LensSetting(85.0, f_number, F_mm, cam.pixel_pitch_mm))
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="288x192,840x560,1680x1120")
    ap.add_argument("--scene", default="demo01")
    ap.add_argument("--f-number", type=float, default=1.8)
    ap.add_argument("--supersample", type=int, default=1)
    a = ap.parse_args()
    print(f"scene {a.scene}, f/{a.f_number}, supersample {a.supersample}")
    print(f"{'size':>11} {'Mpx':>6} {'geometry s':>11} {'DP pair s':>10} {'total s':>8} {'Mpx/s':>7}")
    for text in a.sizes.split(","):
        W, H = (int(v) for v in text.split("x"))
        g, d = bench((W, H), a.scene, a.f_number, a.supersample)
        mpx = W * H / 1e6
        print(f"{W:>5}x{H:<5} {mpx:6.2f} {g:11.2f} {d:10.2f} {g + d:8.2f} {mpx / (g + d):7.2f}")


if __name__ == "__main__":
    main()
