r"""Turn off-the-shelf pinhole RGBD frames into DP pairs (Sec. 4.2 and 5.3.1).

Input layout (one folder per frame)::

    IN/<frame>/image.png        RGB, 8- or 16-bit (sRGB-encoded by default; --encoding linear if not)
    IN/<frame>/depth.png        uint16 depth in mm, 0 = invalid         (or depth.npy, see below)
    IN/<frame>/depth.npy        float depth (z, not ray length) in mm times --depth-scale; 0/NaN/inf = invalid
    IN/<frame>/intrinsics.json  {"fx": px, "fy": px, "cx": px, "cy": px, "width": px, "height": px}

Per frame:

1. **Focus.** A fixed ``focus_mm`` or, as in Sec. 5.3.1, the mean valid depth in a random 60 x 40 px window
   whose centre (the focus point) lies in ``[100, W - 100] x [100, H - 100]`` (at 1024 x 768; scaled with
   the frame's size).
2. **f-number.** Fixed, or drawn from {1.8, 2, 2.8, 4, 5.6}.
3. **Sensor size (5.3.1).** A pinhole dataset gives ``f_pin`` in pixels only; with a pixel pitch ``p`` (mm)
   it is ``f_pin_mm = fx * p`` and Eq. (7) gives :math:`f_{thin} = 1 / (1/F + 1/f_{pin})`. The CoC in
   pixels (Eq. 6 / p) grows monotonically with ``p``, so ``p`` is chosen (bisection on a scale of the
   nominal 36 mm-wide sensor) such that the 99th percentile of ``|CoC|`` at the reference f-number
   (1.8) equals ``max_coc_px`` (the training data's range; default 20 px, the released code's bound),
   which keeps CoC radii inside what the simulator was trained on. Every length stays in its unit: the
   released code passes a focal length in mm where pixels are expected; here Eq. 6 gets mm and divides
   by the pitch in mm.
4. **Simulation** with any registered simulator, in batches of frames of equal size.
5. **Sensor noise** (``--noise``, :mod:`dp5k_common.sensor_noise`): shot plus read noise per channel on both
   views, after the simulator (whose output is an expectation) and before the clip to [0, 1]; by default the
   nominal sensor (variance ``2e-5 I + (1e-3)^2``, the studio's), or ``measured:DATASET`` (measured from a
   dataset's own views), ``diagnosed:REPORT.json`` (what ``dp5k diagnose`` measured), ``shot=..,read=..``, or
   ``none`` (the noise-free views of before). Each frame's noise comes from its own generator, seeded by
   ``(seed, frame name)`` apart from the optics' draws: the same seed gives the same bytes whatever the batch
   size or rank count, and the noise setting never changes the drawn optics. ``sharp`` stays the frame's image, noise
   free: the frames are renders or clean photographs, and a deblurrer's target should be as clean as it can be
   (a captured f/22 ``sharp`` has noise of its own; zero-mean noise in a target only adds variance to the loss).

Output is a format-v1 dataset (one pair per frame, scene = frame, whole frames assigned to
train/val/test with :func:`~dp5k_common.dataset.split_scenes`). Finished pairs are kept: a second run
skips them (resume), and the random draws of a frame depend only on ``(seed, frame name)``.

**Sharded** (``torchrun --nproc_per_node N -m dp5k_cli synthesize IN OUT ...``, any number of nodes): rank
``r`` of ``N`` takes every N-th frame of the sorted list (:func:`dp5k_common.sharding.shard`), so each
frame belongs to exactly one rank and a restarted rank resumes its own share. The split assignment is
computed from *all* frame names, so it does not depend on the rank count. Only rank 0 writes
``dataset.json``: after each of its batches (listing the pairs on disk, as a single process does) and a
last time after a barrier (a gloo process group) that every rank reaches once its share is done, so the
final index equals a single-process run's whatever order the ranks finish in. A crashed rank makes
torchrun stop the others; running the same command again resumes every share.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import zlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist

from dp5k_common.dataset import DatasetReader, PairParams, split_scenes, write_index, write_pair
from dp5k_common.errors import BadInputError, PartialFailureError
from dp5k_common.io import read_image_raw, read_json
from dp5k_common.optics import coc_diameter_px, thin_lens_focal_length_mm
from dp5k_common.progress import progress
from dp5k_common.sensor_noise import NoiseModel, noise_from_spec
from dp5k_common.sharding import RankInfo, rank_info, shard
from dp5k_common.transfer import srgb_to_linear
from dp5k_learn.batch import DPBatch
from dp5k_learn.distributed import resolve_device

from .simulators.catalog import SimulatorSpec

logger = logging.getLogger(__name__)

PAPER_F_NUMBERS: tuple[float, ...] = (1.8, 2.0, 2.8, 4.0, 5.6)
FOCUS_WINDOW_PX = (60, 40)
"""(width, height) of the focus window (Sec. 5.3.1)."""
RANK_WAIT = timedelta(hours=24)
"""How long a rank that finished its share waits at the closing barrier for the slowest rank."""


@dataclass(frozen=True)
class SynthConfig:
    """How frames become DP pairs."""

    simulator: str = "neural"
    """A simulator spec (:class:`~neural_dp.simulators.catalog.SimulatorSpec`): ``disk``, ..., ``neural:CKPT``,
    ``diagnosed:REPORT.json``."""
    checkpoint: str | None = None
    """Completes a bare ``neural`` (the older form of ``neural:CKPT``)."""
    f_numbers: tuple[float, ...] = PAPER_F_NUMBERS
    """One value = fixed; several = one drawn per frame."""
    focus_mm: float | None = None
    """Fixed focus distance; None = the random focus window of Sec. 5.3.1."""
    sensor_width_mm: float = 36.0
    """Nominal sensor width before the 5.3.1 adjustment."""
    max_coc_px: float | None = 20.0
    """Target 99th-percentile |CoC| at f/``reference_f_number``; None = no adjustment (nominal sensor)."""
    reference_f_number: float = 1.8
    encoding: str = "srgb"
    """How image.png is encoded: "srgb" (linearised) or "linear"."""
    depth_scale: float = 1.0
    """depth.npy values times this are mm (1000 for metres)."""
    batch_size: int = 4
    seed: int = 0
    device: str = "auto"
    noise: str = "nominal"
    """The views' sensor noise (:func:`~dp5k_common.sensor_noise.noise_from_spec`): ``nominal``, ``none``,
    ``measured:DATASET``, ``diagnosed:REPORT.json`` or ``shot=..,read=..``."""
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class Frame:
    """One loaded RGBD frame. image (H, W, 3) linear float32; depth_mm (H, W) float32, 0 = invalid."""

    name: str
    image: np.ndarray
    depth_mm: np.ndarray
    fx_px: float
    fy_px: float


def load_frame(folder: Path, encoding: str = "srgb", depth_scale: float = 1.0) -> Frame:
    """Read one frame folder (module docstring). Raises BadInputError naming the file on any problem."""
    img_path = folder / "image.png"
    img = read_image_raw(img_path)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    if img.ndim != 3 or img.shape[2] != 3:
        raise BadInputError(f"must be an RGB image, got shape {img.shape}", where=img_path)
    if img.dtype == np.uint8:
        img01 = img.astype(np.float64) / 255.0
    elif img.dtype == np.uint16:
        img01 = img.astype(np.float64) / 65535.0
    else:
        raise BadInputError(f"must be 8- or 16-bit, got {img.dtype}", where=img_path)
    if encoding == "srgb":
        img01 = srgb_to_linear(img01)
    elif encoding != "linear":
        raise BadInputError(f"unknown encoding {encoding!r} (srgb or linear)", where="synthesize")
    H, W = img01.shape[:2]
    if (folder / "depth.png").is_file():
        d = read_image_raw(folder / "depth.png")
        if d.dtype != np.uint16 or d.ndim != 2:
            raise BadInputError(f"must be single-channel uint16 mm, got {d.dtype} {d.shape}", where=folder / "depth.png")
        depth = d.astype(np.float32)
    elif (folder / "depth.npy").is_file():
        try:
            d = np.load(folder / "depth.npy", allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise BadInputError(f"cannot read ({exc})", where=folder / "depth.npy") from exc
        if d.ndim != 2:
            raise BadInputError(f"must be (H, W), got {d.shape}", where=folder / "depth.npy")
        depth = np.where(np.isfinite(d) & (d > 0), d * depth_scale, 0).astype(np.float32)
    else:
        raise BadInputError("no depth.png or depth.npy", where=folder)
    if depth.shape != (H, W):
        raise BadInputError(f"depth is {depth.shape[1]}x{depth.shape[0]} but image is {W}x{H}", where=folder)
    ipath = folder / "intrinsics.json"
    try:
        intr = read_json(ipath)
    except BadInputError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise BadInputError(f"cannot read ({exc})", where=ipath) from exc
    if not isinstance(intr, dict) or any(k not in intr for k in ("fx", "fy", "width", "height")):
        raise BadInputError("needs fx, fy, cx, cy, width, height (px)", where=ipath)
    if int(intr["width"]) != W or int(intr["height"]) != H:
        raise BadInputError(f"size {intr['width']}x{intr['height']} disagrees with image {W}x{H}", where=ipath)
    fx, fy = float(intr["fx"]), float(intr["fy"])
    if not (fx > 0 and fy > 0 and math.isfinite(fx) and math.isfinite(fy)):
        raise BadInputError(f"fx, fy must be positive, got {fx}, {fy}", where=ipath)
    # the dataset stores whole millimetres (uint16); compute everything from the stored depth
    depth = np.clip(np.rint(depth), 0, 65535).astype(np.float32)
    if not (depth > 0).any():
        raise BadInputError("no valid depth", where=folder)
    return Frame(folder.name, img01.astype(np.float32), depth, fx, fy)


def random_focus(depth_mm: np.ndarray, rng: np.random.Generator, tries: int = 50) -> tuple[float, tuple[float, float]]:
    """Mean valid depth in a random 60 x 40 window (Sec. 5.3.1). Returns (focus_mm, (x, y) window centre)."""
    H, W = depth_mm.shape
    mx, my = int(round(W * 100 / 1024)), int(round(H * 100 / 768))
    ww, wh = min(FOCUS_WINDOW_PX[0], W), min(FOCUS_WINDOW_PX[1], H)
    for _ in range(tries):
        cx = int(rng.integers(min(mx, W - 1), max(W - mx, mx + 1)))
        cy = int(rng.integers(min(my, H - 1), max(H - my, my + 1)))
        x0 = int(np.clip(cx - ww // 2, 0, W - ww))
        y0 = int(np.clip(cy - wh // 2, 0, H - wh))
        win = depth_mm[y0 : y0 + wh, x0 : x0 + ww]
        if (win > 0).any():
            return float(win[win > 0].mean()), (float(cx), float(cy))
    valid = depth_mm[depth_mm > 0]
    return float(np.median(valid)), (W / 2, H / 2)


def optics_for_frame(depth_mm: np.ndarray, fx_px: float, focus_mm: float, width_px: int, cfg: SynthConfig) -> tuple[float, float, float]:
    """Pixel pitch and thin-lens focal length for one frame (module docstring, step 3).

    Returns:
        (pixel_pitch_mm, focal_length_mm (thin lens, Eq. 7), sensor scale relative to the nominal sensor).
    """
    valid = depth_mm[depth_mm > 0]
    sample = valid if valid.size <= 20000 else valid[:: valid.size // 20000 + 1]

    def optics(scale: float) -> tuple[float, float]:
        pitch = scale * cfg.sensor_width_mm / width_px
        return pitch, thin_lens_focal_length_mm(fx_px * pitch, focus_mm)

    def p99(scale: float) -> float:
        pitch, f = optics(scale)
        if not focus_mm > f:
            return math.inf
        return float(np.percentile(np.abs(coc_diameter_px(sample, focus_mm, f, cfg.reference_f_number, pitch)), 99))

    scale = 1.0
    if cfg.max_coc_px is not None and p99(1.0) > 0:
        lo, hi = math.log(1e-4), math.log(1e4)
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if p99(math.exp(mid)) < cfg.max_coc_px:
                lo = mid
            else:
                hi = mid
        scale = math.exp(0.5 * (lo + hi))
    pitch, f = optics(scale)
    return pitch, f, scale


def _frame_rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


NOISE_STREAM = 0x6E6F6973
"""Third word of a frame's noise seed, so that its noise never shares a stream with its optics' draws."""


def _noise_rng(seed: int, name: str) -> np.random.Generator:
    """The generator of one frame's sensor noise: depends only on (seed, frame name)."""
    return np.random.default_rng([seed, zlib.crc32(name.encode()), NOISE_STREAM])


def synthesize(in_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str], cfg: SynthConfig) -> dict[str, Any]:
    """Convert every frame folder of ``in_dir`` into a pair of the dataset ``out_dir`` (resumable, shardable).

    Under torchrun (``RANK`` / ``WORLD_SIZE`` set) this process converts only its share of the frames; see
    the module docstring.

    Returns:
        Summary ``{"written": n, "skipped": n, "failed": {frame: error}, "pairs": n_total, "rank": r,
        "world_size": N}``; written / skipped / failed count this rank's share, pairs the whole dataset.

    Raises:
        BadInputError: a bad simulator spec, a missing checkpoint / report or a bad noise spec (checked first),
            ``in_dir`` has no frame folders, bad options, or ``out_dir`` holds pairs synthesized with other noise.
        PartialFailureError: some frames of this rank's share failed (the others were written; the index
            lists every pair written by any rank).
    """
    spec = SimulatorSpec.parse(cfg.simulator, cfg.checkpoint)
    spec.check_files()
    noise = noise_from_spec(cfg.noise)
    src, out = Path(in_dir), Path(out_dir)
    if not src.is_dir():
        raise BadInputError("input folder not found", where=src)
    frames = sorted(p for p in src.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not frames:
        raise BadInputError("no frame folders (expected IN/<frame>/image.png, depth, intrinsics.json)", where=src)
    if not cfg.f_numbers or any(n <= 0 for n in cfg.f_numbers):
        raise BadInputError(f"f-numbers must be positive, got {cfg.f_numbers}", where="synthesize")
    _check_same_noise(out, noise)
    info = rank_info()
    with _rank_group(info):
        summary = _synthesize_share(out, frames, shard(frames, info), info, spec, cfg, noise)
        _wait_for_all_ranks(info)
        if info.is_main:
            _write_index(out, frames, _split_of(frames, cfg.seed), spec, cfg, noise)
        _wait_for_all_ranks(info)
    summary["pairs"] = len(DatasetReader(out).ids())
    failed = summary["failed"]
    if failed:
        share = f" of rank {info.rank}'s share" if info.enabled else ""
        raise PartialFailureError(
            f"{len(failed)} of {len(frames)} frame(s){share} failed (first: {next(iter(failed.values()))}); "
            "the rest were written",
            where=src,
        )
    return summary


def _check_same_noise(out: Path, noise: NoiseModel | None) -> None:
    """Refuse to add pairs with other noise to a dataset synthesized before (a resumed run must not mix noise
    levels); a dataset written before synthesis had noise records none and was noise free."""
    index = out / "dataset.json"
    if not index.is_file():
        return
    recorded = read_json(index).get("noise_model")
    before = None if recorded is None else NoiseModel.from_json(recorded, index)
    numbers = lambda m: None if m is None else (m.shot_var, m.read_sigma)  # noqa: E731
    if numbers(before) != numbers(noise):
        was = "without noise" if before is None else f"with noise {before.source or before.to_json()}"
        now = "none" if noise is None else noise.source
        raise BadInputError(f"was synthesized {was}; this run asks for --noise {now}: resume with the same --noise "
                            "or write to another folder", where=out)


def _synthesize_share(out: Path, frames: Sequence[Path], mine: Sequence[Path], info: RankInfo, spec: SimulatorSpec,
                      cfg: SynthConfig, noise: NoiseModel | None) -> dict[str, Any]:
    """Write the pairs of this rank's frames ``mine`` that are not on disk yet, with ``noise`` on the views; rank 0
    keeps the index current."""
    device = str(resolve_device(cfg.device, info.local_rank))
    sim = spec.load().to(device)
    sim.eval()
    out.mkdir(parents=True, exist_ok=True)
    split_of = _split_of(frames, cfg.seed)
    done = {f.name for f in mine if (out / "pairs" / pair_id(f.name) / "params.json").is_file()}
    todo = [f for f in mine if f.name not in done]
    _remove_stale_temporaries(out, todo)
    failed: dict[str, str] = {}
    written = 0
    pending: list[tuple[Frame, PairParams, np.ndarray]] = []

    def flush() -> None:
        nonlocal written
        groups: dict[tuple[int, int], list[tuple[Frame, PairParams, np.ndarray]]] = {}
        for item in pending:
            groups.setdefault(item[0].image.shape[:2], []).append(item)
        for items in groups.values():
            batch = _make_batch(items, device)
            with torch.no_grad():
                left, right = sim(batch)
            for k, (frame, params, coc) in enumerate(items):
                views = [v[k].permute(1, 2, 0).cpu().numpy() for v in (left, right)]
                if noise is not None:
                    rng = _noise_rng(cfg.seed, frame.name)
                    views = [noise.sample(v, rng) for v in views]
                write_pair(out, params, sharp=frame.image, left=np.clip(views[0], 0, 1), right=np.clip(views[1], 0, 1),
                           depth_mm=frame.depth_mm, coc_px=np.nan_to_num(coc, nan=0.0), overwrite=True)
                written += 1
        pending.clear()
        if info.is_main:  # one writer of dataset.json; the other ranks' pairs appear in it as they land
            _write_index(out, frames, split_of, spec, cfg, noise)

    desc = f"synthesize (rank {info.rank}/{info.world_size})" if info.enabled else "synthesize"
    for folder in progress(todo, desc=desc, unit="frame"):
        try:
            frame = load_frame(folder, cfg.encoding, cfg.depth_scale)
            rng = _frame_rng(cfg.seed, frame.name)
            if cfg.focus_mm is not None:
                focus, point = float(cfg.focus_mm), (frame.image.shape[1] / 2, frame.image.shape[0] / 2)
            else:
                focus, point = random_focus(frame.depth_mm, rng)
            n = float(cfg.f_numbers[0] if len(cfg.f_numbers) == 1 else cfg.f_numbers[int(rng.integers(len(cfg.f_numbers)))])
            H, W = frame.depth_mm.shape
            pitch, f_thin, scale = optics_for_frame(frame.depth_mm, frame.fx_px, focus, W, cfg)
            if not focus > f_thin:
                raise BadInputError(f"focus distance {focus:.1f} mm is not beyond the focal length {f_thin:.1f} mm", where=folder)
            coc = coc_diameter_px(frame.depth_mm, focus, f_thin, n, pitch).astype(np.float32)
            params = PairParams(
                pair_id=pair_id(frame.name), scene=frame.name, camera="synth", f_number=n, focus_distance_mm=focus,
                focal_length_mm=f_thin, pixel_pitch_mm=pitch, focus_point_px=point, image_size=(W, H),
                extra={"synthetic": True, "sharp_f_number": 0.0, "simulator": str(spec), "source_frame": frame.name,
                       "pinhole_fx_px": frame.fx_px, "sensor_scale": scale,
                       "noise": None if noise is None else noise.to_json(), **cfg.extra},
            )
            pending.append((frame, params, coc))
        except BadInputError as exc:
            failed[folder.name] = exc.one_line()
            logger.warning("skipping frame %s: %s", folder.name, exc.one_line())
            continue
        if len(pending) >= cfg.batch_size:
            flush()
    flush()
    return {"written": written, "skipped": len(done), "failed": failed, "rank": info.rank,
            "world_size": info.world_size}


def _remove_stale_temporaries(out: Path, todo: Sequence[Path]) -> None:
    """Delete the half-written temporary folders that a killed run left for the frames this rank will write.

    :func:`~dp5k_common.dataset.write_pair` builds a pair in ``pairs/.tmp-<pair_id>-<8 random characters>``
    and renames it when complete. Only this rank writes its frames, so their temporaries are its own; the
    exact name pattern keeps another pair's (``<pair_id>-x``) out of reach.
    """
    pairs = out / "pairs"
    if not pairs.is_dir():
        return
    for f in todo:
        stale = re.compile(rf"\.tmp-{re.escape(pair_id(f.name))}-[a-z0-9_]{{8}}")
        for tmp in pairs.glob(f".tmp-{pair_id(f.name)}-*"):
            if tmp.is_dir() and stale.fullmatch(tmp.name):
                logger.info("removing %s, left by an interrupted run", tmp)
                shutil.rmtree(tmp)


def pair_id(frame: str) -> str:
    """The dataset pair id of a frame folder name (characters outside ``[A-Za-z0-9._-]`` become ``_``)."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", frame)
    return safe if safe[0].isalnum() else "f" + safe


def _split_of(frames: Sequence[Path], seed: int) -> dict[str, str]:
    """Frame name -> split, from all frames (never one rank's share, so any rank count gives the same split)."""
    scene_split = split_scenes([f.name for f in frames], seed=seed)
    return {s: name for name, scenes in scene_split.items() for s in scenes}


@contextmanager
def _rank_group(info: RankInfo) -> Iterator[None]:
    """A gloo process group for the closing barriers when sharded (torchrun's rendezvous); nothing alone."""
    if not info.enabled or dist.is_initialized():
        yield
        return
    try:
        dist.init_process_group("gloo", rank=info.rank, world_size=info.world_size, timeout=RANK_WAIT)
    except (ValueError, RuntimeError) as exc:
        raise BadInputError(f"RANK={info.rank} of WORLD_SIZE={info.world_size} but no torchrun rendezvous "
                            f"(start with torchrun, or unset RANK): {exc}", where="environment") from exc
    try:
        yield
    finally:
        dist.destroy_process_group()


def _wait_for_all_ranks(info: RankInfo) -> None:
    if info.enabled:
        dist.barrier()


def _make_batch(items: Sequence[tuple[Frame, PairParams, np.ndarray]], device: str) -> DPBatch:
    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a))

    sharp = torch.stack([t(f.image.transpose(2, 0, 1)) for f, _, _ in items])
    valid = torch.stack([t(f.depth_mm > 0)[None] for f, _, _ in items])
    coc = torch.stack([t(np.nan_to_num(c, nan=0.0).astype(np.float32))[None] for _, _, c in items])
    depth = torch.stack([t(f.depth_mm)[None] for f, _, _ in items])
    P = [p for _, p, _ in items]
    f32 = torch.float32
    return DPBatch(
        sharp=sharp, coc_px=coc, depth_mm=depth, valid=valid,
        f_number=torch.tensor([p.f_number for p in P], dtype=f32),
        focus_distance_mm=torch.tensor([p.focus_distance_mm for p in P], dtype=f32),
        focal_length_mm=torch.tensor([p.focal_length_mm for p in P], dtype=f32),
        pixel_pitch_mm=torch.tensor([p.pixel_pitch_mm for p in P], dtype=f32),
        focus_point_px=torch.tensor([p.focus_point_px for p in P], dtype=f32),
        pair_ids=tuple(p.pair_id for p in P),
        sharp_f_number=torch.tensor([p.sharp_f_number for p in P], dtype=f32),  # 0: the frames are all-in-focus
    ).to(device)


def _write_index(out: Path, frames: Sequence[Path], split_of: dict[str, str], spec: SimulatorSpec, cfg: SynthConfig,
                 noise: NoiseModel | None) -> None:
    """dataset.json listing, in frame order, every frame whose pair is on disk, in its split, with the views' noise
    model (``noise_model``; null: noise free)."""
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    for f in frames:
        pid = pair_id(f.name)
        if (out / "pairs" / pid / "params.json").is_file():
            splits[split_of[f.name]].append(pid)
    write_index(out, splits, source="dp5k synthesize", simulator=str(spec),
                synth_config=json.loads(json.dumps({k: v for k, v in cfg.__dict__.items() if k != "extra"}, default=str)),
                noise_model=None if noise is None else noise.to_json())
