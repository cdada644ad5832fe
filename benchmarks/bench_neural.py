"""Neural DP at the paper's scale: tiled inference at 1680 x 1120 (seconds, peak memory), training samples per
second, and ``dp5k synthesize`` frames per second with one process and with torchrun ranks.

Usage::

    python benchmarks/bench_neural.py [--parts read,inference,untiled,train,synth] [--device cpu|cuda]
                                      [--size 1680x1120] [--channels 64] [--levels 4] [--tile 512]
                                      [--train-crop 256] [--train-batch 2] [--synth-frames 8] [--ranks 2]
                                      [--quick]

Prints one Markdown table; every row carries the date, the load average (1/5/15 min, taken as the row's
measurement ends) and the git commit. Each figure is set against a floor measured in the same run:

* ``read``: reading one paper-size frame (image.png, depth.png, intrinsics.json) with
  :func:`neural_dp.synthesize.load_frame`, the least any pass over a frame costs.
* ``inference``: :class:`~neural_dp.simulators.neural.NeuralDPSimulator` (the paper's U-Net: 64 base channels,
  4 levels, 5 x 5 kernels) on a textured 1680 x 1120 scene, tiled (``--tile`` px tiles plus the network's
  receptive radius as halo), in a fresh process: seconds and the growth of the process's peak RSS (CPU) or
  the CUDA allocator's peak. The row also gives the pixels the tiles compute per image pixel (halo overhead).
* ``untiled``: the floor for inference: one whole-image pass of the same network (no halo), its seconds and
  peak memory, in its own fresh process.
* ``train``: samples per second of the Neural DP training step (:func:`dp5k_learn.training.optimiser_step`:
  forward, Eq. 8 loss, backward, Adam) on ``--train-crop`` px crops, against one forward pass of the same batch (the floor).
* ``synth``: frames per second of ``dp5k synthesize`` (``--synth-simulator``, default ``base``) on
  ``--synth-frames`` generated 640 x 480 RGBD frames: one process, then ``torchrun --nproc_per_node --ranks``
  (one thread per process in both, so their ratio is the scaling with ranks), against reading the frames.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np
import torch

from dp5k_common.optics import coc_diameter_px
from dp5k_learn.batch import DPBatch
from dp5k_learn.training import optimiser_step
from dp5k_testing.torchrun import run_torchrun
from neural_dp.config import TrainConfig
from neural_dp.model import ModelConfig
from neural_dp.simulators.neural import NeuralDPSimulator, model_inputs
from neural_dp.synthesize import SynthConfig, load_frame, synthesize
from neural_dp.train import forward_fn, loss_fn
from run_info import device_suffix, recording

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("read", "inference", "untiled", "train", "synth")
SYNTH_FRAME_PX = (640, 480)
"""(width, height) of the generated frames that synthesis is timed on."""
FOCUS_MM = 2000.0
FOCAL_LENGTH_MM = 85.0
SENSOR_WIDTH_MM = 36.0
F_NUMBER = 1.8


def commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                               text=True, check=True).stdout.strip()
        return out + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def stamp() -> str:
    """``date | load 1/5/15 | commit`` cells for a row, taken now."""
    load = "/".join(f"{v:.1f}" for v in os.getloadavg())
    return f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} | {load} | {commit()}"


def scene(W: int, H: int, device: str, batch: int = 1, seed: int = 0) -> DPBatch:
    """A textured image with a left-to-right depth ramp (1 m .. 10 m, focus 2 m), DP5K optics (85 mm, f/1.8,
    36 mm sensor); ``left`` / ``right`` are half the sharp image (targets for the training step)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:H, :W] / max(H, W)
    tex = 0.5 + 0.25 * np.sin(40 * xx[..., None] * np.array([1, 1.3, 0.7])) * np.cos(31 * yy[..., None])
    sharp = np.clip(tex + rng.normal(0, 0.05, (H, W, 3)), 0, 1).astype(np.float32)
    depth_mm = np.tile(np.geomspace(1000, 10000, W), (H, 1)).astype(np.float32)
    pitch_mm = SENSOR_WIDTH_MM / W
    coc_px = coc_diameter_px(depth_mm, FOCUS_MM, FOCAL_LENGTH_MM, F_NUMBER, pitch_mm).astype(np.float32)

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).expand(batch, *a.shape).contiguous()

    s = t(sharp.transpose(2, 0, 1))
    z = torch.zeros(batch)
    return DPBatch(sharp=s, coc_px=t(coc_px[None]), depth_mm=t(depth_mm[None]),
                   valid=torch.ones(batch, 1, H, W, dtype=torch.bool), f_number=z + F_NUMBER,
                   focus_distance_mm=z + FOCUS_MM, focal_length_mm=z + FOCAL_LENGTH_MM, pixel_pitch_mm=z + pitch_mm,
                   focus_point_px=torch.zeros(batch, 2), left=0.5 * s, right=0.5 * s).to(device)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def peak_mib(device: str, rss0_kib: int) -> float:
    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated() / 2**20
    return (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0_kib) / 1024


def tile_overhead(sim: NeuralDPSimulator, W: int, H: int) -> float:
    """Pixels the tiles compute (tile plus halo, clipped to the image) per image pixel; 1 when untiled."""
    tile, m = sim.cfg.tile_px, sim.net.multiple
    if tile <= 0 or (W <= tile and H <= tile):
        return 1.0
    tile = max(m, tile // m * m)
    halo = -(-max(sim.cfg.tile_margin_px, sim.net.receptive_radius_px) // m) * m

    def extent(n: int) -> int:
        return sum(min(n, s + tile + halo) - max(0, s - halo) for s in range(0, n, tile))

    return extent(W) * extent(H) / (W * H)


def inference_child(device: str, W: int, H: int, channels: int, levels: int, tile: int) -> dict[str, float]:
    """One tiled (``tile`` > 0) or whole-image (``tile`` = 0) pass, in this fresh process."""
    sim = NeuralDPSimulator(ModelConfig(base_channels=channels, levels=levels, tile_px=tile)).to(device).eval()
    batch = scene(W, H, device)
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with torch.no_grad():
        sync(device)
        t0 = time.perf_counter()
        sim(batch)
        sync(device)
        seconds = time.perf_counter() - t0
    return {"seconds": seconds, "peak_mib": peak_mib(device, rss0), "overhead": tile_overhead(sim, W, H)}


def run_child(args: argparse.Namespace, tile: int) -> dict[str, float]:
    cmd = [sys.executable, __file__, "--_child", str(tile), "--device", args.device, "--size", args.size,
           "--channels", str(args.channels), "--levels", str(args.levels)]
    child = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(child.stdout.strip().splitlines()[-1])


def write_frames(root: Path, n: int, W: int, H: int) -> None:
    """``n`` RGBD frame folders in ``dp5k synthesize``'s input layout (8-bit sRGB, uint16 mm depth)."""
    rng = np.random.default_rng(0)
    for i in range(n):
        f = root / f"frame_{i:04d}"
        f.mkdir(parents=True)
        b = scene(W, H, "cpu", seed=i)
        img = (b.sharp[0].permute(1, 2, 0).numpy() ** (1 / 2.2) * 255).astype(np.uint8)
        cv2.imwrite(str(f / "image.png"), img[..., ::-1])
        depth = b.depth_mm[0, 0].numpy() * rng.uniform(0.8, 1.2)
        cv2.imwrite(str(f / "depth.png"), depth.astype(np.uint16))
        (f / "intrinsics.json").write_text(json.dumps({"fx": 1.2 * W, "fy": 1.2 * W, "cx": W / 2, "cy": H / 2,
                                                       "width": W, "height": H}))


def time_read(root: Path) -> float:
    """Seconds to read every frame of ``root`` once."""
    t0 = time.perf_counter()
    for f in sorted(root.iterdir()):
        load_frame(f)
    return time.perf_counter() - t0


def bench_read(W: int, H: int) -> tuple[str, str, str]:
    with tempfile.TemporaryDirectory() as tmp:
        write_frames(Path(tmp), 1, W, H)
        seconds = time_read(Path(tmp))
    return f"read one frame (load_frame) | {W}x{H} png + depth png", f"{seconds:.2f} s", "(floor)"


def bench_train(args: argparse.Namespace) -> tuple[str, str, str]:
    cfg = TrainConfig()
    sim = NeuralDPSimulator(ModelConfig(base_channels=args.channels, levels=args.levels)).to(args.device).train()
    opt = torch.optim.Adam(sim.net.parameters(), lr=cfg.optim.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda _: 1.0)
    batch = scene(args.train_crop, args.train_crop, args.device, batch=args.train_batch)

    def step() -> None:
        optimiser_step(sim.net, opt, sched, batch, forward_fn(sim.net, sim.cfg.coc_scale_px),
                       loss_fn(sim.net.reach_px, cfg.optim.grad_weight), grad_clip=cfg.optim.grad_clip,
                       amp=cfg.optim.amp and args.device.startswith("cuda"))

    step()  # warm-up: allocations, Adam state
    sync(args.device)
    t0 = time.perf_counter()
    for _ in range(args.train_steps):
        step()
    sync(args.device)
    per_step = (time.perf_counter() - t0) / args.train_steps
    with torch.no_grad():
        t0 = time.perf_counter()
        sim.net(batch.sharp, model_inputs(batch, sim.cfg.coc_scale_px))
        sync(args.device)
        forward = time.perf_counter() - t0
    what = (f"training step (optimiser_step) | {args.train_crop}x{args.train_crop} crops, batch {args.train_batch}, "
            f"{args.channels} ch, {args.levels} levels, {args.train_steps} timed step(s)")
    return what, f"{args.train_batch / per_step:.3f} samples/s ({per_step:.1f} s/step)", \
        f"forward alone {args.train_batch / forward:.3f} samples/s"


def bench_synth(args: argparse.Namespace) -> list[tuple[str, str, str]]:
    W, H = SYNTH_FRAME_PX
    n = args.synth_frames
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "in"
        write_frames(src, n, W, H)
        read_s = time_read(src)
        cfg = SynthConfig(simulator=args.synth_simulator, f_numbers=(F_NUMBER,), batch_size=1)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # as each rank below: the ratio is the rank scaling
        t0 = time.perf_counter()
        synthesize(src, Path(tmp) / "one", cfg)
        one = time.perf_counter() - t0
        torch.set_num_threads(threads)
        settings = f"{n} frames {W}x{H}, --simulator {args.synth_simulator}"
        rows.append((f"synthesize, 1 process (1 thread) | {settings}", f"{n / one:.2f} frames/s",
                     f"reading the frames {n / read_s:.1f} frames/s"))
        t0 = time.perf_counter()
        run_torchrun(["synthesize", src, Path(tmp) / "ranks", "--simulator", args.synth_simulator, "--f-number", F_NUMBER,
                      "--batch-size", "1"], nproc=args.ranks, timeout_s=24 * 3600, check=True)
        many = time.perf_counter() - t0
        same = (Path(tmp) / "one" / "dataset.json").read_text() == (Path(tmp) / "ranks" / "dataset.json").read_text()
        rows.append((f"synthesize, torchrun {args.ranks} ranks (1 thread each) | {settings}; wall time incl. "
                     f"start-up; index equal to 1 process: {same}", f"{n / many:.2f} frames/s", "same floor"))
        shutil.rmtree(Path(tmp) / "ranks")
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", default=",".join(PARTS), help="comma-separated subset of " + ", ".join(PARTS))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", default="1680x1120", help="WxH of the inference scene")
    ap.add_argument("--channels", type=int, default=64, help="U-Net base channels (paper: 64)")
    ap.add_argument("--levels", type=int, default=4, help="U-Net levels (paper: 4)")
    ap.add_argument("--tile", type=int, default=ModelConfig().tile_px, help="inference tile side, px")
    ap.add_argument("--train-crop", type=int, default=TrainConfig().data.crop_px)
    ap.add_argument("--train-batch", type=int, default=2, help="(dp5k train's default is 8; per-sample cost is similar)")
    ap.add_argument("--train-steps", type=int, default=1, help="timed steps after one warm-up step")
    ap.add_argument("--synth-frames", type=int, default=8)
    ap.add_argument("--synth-simulator", default="base")
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="small sizes and network, for a smoke run")
    ap.add_argument("--_child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.quick:
        args.size, args.channels, args.tile, args.train_crop, args.synth_frames = "384x256", 8, 128, 64, 4
    W, H = (int(v) for v in args.size.split("x"))
    if args._child is not None:
        print(json.dumps(inference_child(args.device, W, H, args.channels, args.levels, args._child)))
        return 0
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        print(f"bench_neural: unknown part(s) {', '.join(unknown)}; choose from {', '.join(PARTS)}", file=sys.stderr)
        return 2
    dev = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"CPU, {torch.get_num_threads()} threads"
    print(f"device: {dev} ({os.cpu_count()} cores); torch {torch.__version__}; no GPU figures unless --device cuda",
          flush=True)
    print("| measurement | settings | figure | floor / peer (same run) | date (UTC) | load 1/5/15 | commit |")
    print("|---|---|---|---|---|---|---|", flush=True)
    net = f"{args.channels} ch, {args.levels} levels"
    if "read" in parts:
        what, fig, floor = bench_read(W, H)
        print(f"| {what} | {fig} | {floor} | {stamp()} |", flush=True)
    if "inference" in parts:
        r = run_child(args, args.tile)
        print(f"| Neural DP inference, tiled | {W}x{H}, {net}, {args.tile} px tiles + receptive-radius halo "
              f"({r['overhead']:.2f} px computed per px) | {r['seconds']:.1f} s, peak {r['peak_mib']:.0f} MiB | "
              f"{W * H / 1e6 / r['seconds']:.3f} MP/s | {stamp()} |", flush=True)
    if "untiled" in parts:
        r = run_child(args, 0)
        print(f"| Neural DP inference, whole image (floor) | {W}x{H}, {net}, one pass | {r['seconds']:.1f} s, peak "
              f"{r['peak_mib']:.0f} MiB | (floor) | {stamp()} |", flush=True)
    if "train" in parts:
        what, fig, floor = bench_train(args)
        print(f"| {what} | {fig} | {floor} | {stamp()} |", flush=True)
    if "synth" in parts:
        for what, fig, floor in bench_synth(args):
            print(f"| {what} | {fig} | {floor} | {stamp()} |", flush=True)
    return 0


if __name__ == "__main__":
    parts = sys.argv[sys.argv.index("--parts") + 1].replace(",", "-") if "--parts" in sys.argv[:-1] else ""
    with recording(f"speed-neural{device_suffix(sys.argv)}{'-' + parts if parts else ''}", "Neural DP at paper scale: tiled inference, training, synthesis",
                   enabled="--quick" not in sys.argv and "--_child" not in sys.argv):
        raise SystemExit(main())
