"""Speed of every DP simulator, Neural DP inference at 1680 x 1120 with its peak memory, training throughput.

Usage::

    python benchmarks/bench_simulators.py [--device cpu|cuda] [--peer-size 1680x1120] [--dataset DIR]
        [--simulators disk,butterworth,raytrace,base] [--no-neural] [--quick]

Prints a Markdown table (recorded in benchmarks/results/, shown in docs/results.md); every row carries the date,
the machine's 1-minute load average and the git commit. The peers' scene is the first pair of ``--dataset``
(e.g. one studio pair at 1680 x 1120, as ``dp5k evaluate --max-pairs 1`` times it), or else synthetic: a
textured image, a depth ramp from 1 m to 10 m focused at 2 m, and the DP5K optics (85 mm, f/1.8, 36 mm
sensor), so CoC diameters span the paper's range scaled to the image width. Two floors are measured in the
same run: reading the pair once (with ``--dataset``) and one FFT convolution of the frame's 3 colour
channels with one 75-px PSF (what a layered renderer pays per frame-sized layer). Peak memory is the CUDA
allocator's peak on GPU, and the growth of the process's peak RSS on CPU (measured in a fresh process).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch


from dp5k_common.optics import coc_diameter_px
from dp5k_learn.batch import DPBatch
from dp5k_learn.data import DPPairDataset, collate_dp
from dp5k_learn.losses import dp_loss
from neural_dp.model import ModelConfig
from neural_dp.registry import PEERS, get_simulator
from neural_dp.simulators.neural import NeuralDPSimulator, model_inputs
from run_info import device_suffix, recording


def scene(W: int, H: int, device: str, seed: int = 0) -> DPBatch:
    """A textured image with a left-to-right depth ramp (1 m .. 10 m, focus 2 m), DP5K optics at f/1.8."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:H, :W] / max(H, W)
    tex = 0.5 + 0.25 * np.sin(40 * xx[..., None] * np.array([1, 1.3, 0.7])) * np.cos(31 * yy[..., None])
    sharp = np.clip(tex + rng.normal(0, 0.05, (H, W, 3)), 0, 1).astype(np.float32)
    depth = np.tile(np.geomspace(1000, 10000, W), (H, 1)).astype(np.float32)
    pitch = 36.0 / W
    coc = coc_diameter_px(depth, 2000.0, 85.0, 1.8, pitch).astype(np.float32)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    z = torch.zeros(1)
    return DPBatch(sharp=t(sharp.transpose(2, 0, 1))[None], coc_px=t(coc)[None, None], depth_mm=t(depth)[None, None],
                   valid=torch.ones(1, 1, H, W, dtype=torch.bool), f_number=z + 1.8, focus_distance_mm=z + 2000,
                   focal_length_mm=z + 85, pixel_pitch_mm=z + pitch, focus_point_px=torch.zeros(1, 2)).to(device)


def dataset_pair(root: str, device: str) -> DPBatch:
    """The first pair of the dataset at ``root`` (any split), as a batch of one."""
    for split in ("test", "val", "train"):
        try:
            ds = DPPairDataset(root, split, cache=False)
        except Exception:  # an empty split: try the next
            continue
        return collate_dp([ds[0]]).to(device)
    raise SystemExit(f"{root}: no pair in any split")


def fft_floor(batch: DPBatch, device: str, psf_px: int = 75) -> float:
    """Seconds for one zero-padded FFT convolution of the frame's 3 channels with one ``psf_px`` PSF."""
    from scipy.fft import next_fast_len

    H, W = batch.sharp.shape[-2:]
    Hp, Wp = next_fast_len(H + psf_px, real=True), next_fast_len(W + psf_px, real=True)
    psf = torch.rand(psf_px, psf_px, device=device)

    def conv() -> torch.Tensor:
        return torch.fft.irfft2(torch.fft.rfft2(batch.sharp.float(), s=(Hp, Wp)) * torch.fft.rfft2(psf, s=(Hp, Wp)), s=(Hp, Wp))

    return time_call(conv, device, 2)


def stamp() -> str:
    """Date, 1-minute load average and git commit, printed beside every figure."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    return f"{datetime.datetime.now():%Y-%m-%d %H:%M} | {os.getloadavg()[0]:.1f} | {commit}"


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_call(fn, device: str, repeat: int) -> float:
    fn()
    sync(device)
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    sync(device)
    return (time.perf_counter() - t0) / repeat


def neural_inference(device: str, W: int, H: int, channels: int) -> dict[str, float]:
    """Run in a fresh process on CPU so the peak RSS belongs to this measurement alone."""
    sim = NeuralDPSimulator(ModelConfig(base_channels=channels)).to(device).eval()
    batch = scene(W, H, device)
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with torch.no_grad():
        t = time_call(lambda: sim(batch), device, 1)
    peak = (torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda")
            else (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024)
    return {"seconds": t, "mp_per_s": W * H / 1e6 / t, "peak_mib": peak}


def train_throughput(device: str, crop: int, batch: int, channels: int, steps: int) -> float:
    sim = NeuralDPSimulator(ModelConfig(base_channels=channels)).to(device).train()
    opt = torch.optim.Adam(sim.net.parameters(), lr=5e-4)
    b = scene(crop, crop, device)
    b = DPBatch(**{k: (v.expand(batch, *v.shape[1:]).contiguous() if isinstance(v, torch.Tensor) else v)
                   for k, v in b.__dict__.items()})
    left_gt = right_gt = 0.5 * b.sharp
    mask = b.valid.float()

    def step() -> None:
        left, right = sim.net(b.sharp, model_inputs(b, 10.0))
        loss = dp_loss(left, right, left_gt, right_gt, mask)
        opt.zero_grad()
        loss.backward()
        opt.step()

    return batch / time_call(step, device, steps)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--peer-size", default="1680x1120", help="WxH of the synthetic scene for the handcrafted simulators")
    ap.add_argument("--dataset", default=None, help="time the handcrafted simulators on this dataset's first pair instead")
    ap.add_argument("--simulators", default=",".join(list(PEERS) + ["base"]), help="comma-separated handcrafted simulators")
    ap.add_argument("--no-neural", action="store_true", help="skip Neural DP inference and training")
    ap.add_argument("--neural-size", default="1680x1120")
    ap.add_argument("--channels", type=int, default=64, help="U-Net base channels (paper: 64)")
    ap.add_argument("--train-crop", type=int, default=256)
    ap.add_argument("--train-batch", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="small sizes, for a smoke run")
    ap.add_argument("--_neural_child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.quick:
        args.peer_size, args.neural_size, args.channels, args.train_crop, args.train_batch = "192x128", "384x256", 16, 64, 2
    pw, ph = (int(v) for v in args.peer_size.split("x"))
    nw, nh = (int(v) for v in args.neural_size.split("x"))
    if args._neural_child:
        print(json.dumps(neural_inference(args.device, nw, nh, args.channels)))
        return 0
    torch.manual_seed(0)
    if args.dataset:
        t0 = time.perf_counter()
        batch = dataset_pair(args.dataset, args.device)
        read_s = time.perf_counter() - t0
    else:
        batch = scene(pw, ph, args.device)
    ph, pw = batch.sharp.shape[-2:]
    coc = batch.coc_px[batch.valid].abs()
    dev = torch.cuda.get_device_name() if args.device.startswith("cuda") else f"CPU, {torch.get_num_threads()} threads"
    print(f"device: {dev}; torch {torch.__version__}; peer scene {args.dataset or 'synthetic'}, |CoC| max "
          f"{float(coc.max()):.1f} px, median {float(coc.median()):.1f} px", flush=True)
    print("| simulator | size | MP/s | s/image | peak MiB | date | load | commit |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    if args.dataset:
        print(f"| floor: read the pair once | {pw}x{ph} | {pw * ph / 1e6 / read_s:.3f} | {read_s:.2f} | | {stamp()} |", flush=True)
    t = fft_floor(batch, args.device)
    print(f"| floor: one FFT convolution (3 channels, 75 px PSF) | {pw}x{ph} | {pw * ph / 1e6 / t:.3f} | {t:.2f} | | {stamp()} |",
          flush=True)
    for name in [n for n in args.simulators.split(",") if n]:
        sim = get_simulator(name).to(args.device).eval()
        if name == "raytrace":  # numba compiles once per machine and code version, then loads from its disk cache
            tiny = scene(16, 12, args.device)
            t0 = time.perf_counter()
            with torch.no_grad():
                sim(tiny)
            print(f"| raytrace: compile or load the numba kernel (once per process, not per pair) | 16x12 | | "
                  f"{time.perf_counter() - t0:.2f} | | {stamp()} |", flush=True)
        sync(args.device)
        t0 = time.perf_counter()
        with torch.no_grad():  # one cold call, as `dp5k evaluate --max-pairs 1` times it (seconds_per_pair)
            sim(batch)
        sync(args.device)
        t = time.perf_counter() - t0
        print(f"| {name} | {pw}x{ph} | {pw * ph / 1e6 / t:.3f} | {t:.2f} | | {stamp()} |", flush=True)
    if args.no_neural:
        return 0
    child = subprocess.run([sys.executable, __file__, "--_neural_child", "--device", args.device, "--neural-size",
                            args.neural_size, "--channels", str(args.channels)], capture_output=True, text=True, check=True)
    nres = json.loads(child.stdout.strip().splitlines()[-1])
    print(f"| neural (inference, base channels {args.channels}) | {nw}x{nh} | {nres['mp_per_s']:.3f} | "
          f"{nres['seconds']:.2f} | {nres['peak_mib']:.0f} | {stamp()} |", flush=True)
    sps = train_throughput(args.device, args.train_crop, args.train_batch, args.channels, args.repeat)
    print(f"\nNeural DP training: {sps:.2f} samples/s ({args.train_crop}x{args.train_crop} crops, batch "
          f"{args.train_batch}, base channels {args.channels}; {stamp()})", flush=True)
    return 0


if __name__ == "__main__":
    with recording(f"speed-simulators{device_suffix(sys.argv)}", "Simulators: seconds per image, Neural DP inference and training",
                   enabled="--quick" not in sys.argv and "--_neural_child" not in sys.argv):
        raise SystemExit(main())
